"""``abh3 scan`` on the simulator: five drives at scattered addresses, both generations."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from abh3_supervisor.clients.cli import main
from abh3_supervisor.clients.scan import Findings, Scanner, guess_generation
from abh3_supervisor.config import parse_config
from abh3_supervisor.config.model import SimConfig, VelocityModel
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.protocol.frames import Generation
from abh3_supervisor.simulator import SimBus
from abh3_supervisor.simulator.drive import SimDrive
from tests.wacousb_emulator import AdapterEmulator

# address: (generation, broadcast group, velocity model)
FIVE = {
    1: (Generation.G2021, 5, VelocityModel.TRAVEL),
    7: (Generation.G2023, 0, VelocityModel.MOTOR),
    42: (Generation.G2021, 31, VelocityModel.MOTOR),
    130: (Generation.G2023, 12, VelocityModel.TRAVEL),
    253: (Generation.G2021, 5, VelocityModel.TRAVEL),
}


class SimNode:
    """Simulated drives on a virtual bus, stepped on their own thread in real time; every
    frame they receive is kept (to prove nothing but requests reached them)."""

    def __init__(
        self, channel: str, cfg: SimConfig, drives: dict[int, tuple[Generation, int, VelocityModel]]
    ) -> None:
        now = time.monotonic()
        self.sim = SimBus(
            SimDrive(a, group=g, generation=gen, model=m, cfg=cfg, now=now)
            for a, (gen, g, m) in drives.items()
        )
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.heard: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.005)
            now = time.monotonic()
            if msg is not None:
                self.heard.append(msg.arbitration_id)
                self.sim.on_frame(msg.arbitration_id, bytes(msg.data), now)
            for arbitration_id, data in self.sim.poll(now):
                self.bus.send(can.Message(arbitration_id=arbitration_id, data=data))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.bus.shutdown()


@pytest.fixture
def five() -> Iterator[SimNode]:
    node = SimNode("scan-five", SimConfig(reply_latency_ms=0.0), FIVE)
    yield node
    node.close()


def test_guess_generation_from_dp0_replies() -> None:
    assert guess_generation(frames.encode_dp0_reply_2021(500, 300, 400, 100)) == (
        Generation.G2021,
        True,
    )
    assert guess_generation(frames.encode_dp0_reply_2021(0, 0, 0, 0)) == (Generation.G2021, False)
    assert guess_generation(frames.encode_dp0_reply_2023(0, 0, 0x80000000)) == (
        Generation.G2023,
        True,
    )
    assert guess_generation(frames.encode_dp0_reply_2023(500, -500, 0x22000303)) == (
        Generation.G2023,
        True,
    )


@pytest.mark.wallclock
def test_scan_finds_exactly_the_simulated_drives_and_sends_only_requests(five: SimNode) -> None:
    with can.Bus(interface="virtual", channel="scan-five") as bus:
        scanner = Scanner(bus, host=2)
        t0 = time.monotonic()
        found = scanner.run()
        took = time.monotonic() - t0
    assert set(found.drives) == set(FIVE)
    for address, (generation, group, model) in FIVE.items():
        d = found.drives[address]
        assert (d.generation, d.generation_certain, d.group, d.hosts) == (
            generation,
            True,
            group,
            {2},
        )
        assert d.travel_model is (model is VelocityModel.TRAVEL)
    assert five.heard and all(ids.CanId.from_int(i).pf == ids.PF_REQUEST for i in five.heard)
    assert all(d.cmd_raw == (0, 0) and d.inputs == 0 for d in five.sim.drives.values())
    assert scanner.sent == len(five.heard) < 300 and took < 3.0
    print(f"scan: {len(found.drives)} drives, {scanner.sent} requests, {took:.2f} s")


@pytest.mark.wallclock
def test_the_cli_writes_a_starting_configuration(
    five: SimNode, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["scan", "--interface", "virtual", "--channel", "scan-five", "--yaml"]) == 0
    out, err = capsys.readouterr()
    config = parse_config(out, "scanned.yaml")
    units = {u.abh3_id: u for u in config.units.values()}
    assert set(units) == set(FIVE)
    for address, (generation, group, model) in FIVE.items():
        u = units[address]
        assert (u.protocol, u.brd_group, u.velocity_model, u.host_id, u.role.value) == (
            generation,
            group,
            model,
            2,
            "monitor",
        )
    bus = config.buses["bus0"]
    assert (bus.interface, bus.channel, bus.bitrate, bus.simulate) == (
        "virtual",
        "scan-five",
        500000,
        None,
    )
    assert "5 drive(s)" in err and "no command" in err
    for address in FIVE:
        assert any(line.split()[0] == str(address) for line in err.splitlines() if line.strip())


@pytest.mark.wallclock
def test_listen_only_sends_nothing_and_learns_from_traffic(
    capsys: pytest.CaptureFixture[str],
) -> None:
    chatty = SimConfig(reply_latency_ms=0.0, dp0_period_ms=20, broadcast_period_ms=50)
    node = SimNode("scan-listen", chatty, {7: FIVE[7], 42: FIVE[42]})
    try:
        assert (
            main(
                [
                    "scan",
                    "--interface",
                    "virtual",
                    "--channel",
                    "scan-listen",
                    "--listen-only",
                    "--listen",
                    "0.3",
                ]
            )
            == 0
        )
    finally:
        node.close()
    assert node.heard == []  # not one frame from us
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in out.splitlines()[1:3]}
    assert rows["7"][1:4] == ["2023", "0", "motor"] and rows["42"][1:4] == ["2021", "31", "motor"]


@pytest.mark.wallclock
def test_listen_only_on_a_silent_bus_finds_nothing(capsys: pytest.CaptureFixture[str]) -> None:
    node = SimNode("scan-quiet", SimConfig(), {1: FIVE[1]})
    try:
        assert (
            main(
                [
                    "scan",
                    "--interface",
                    "virtual",
                    "--channel",
                    "scan-quiet",
                    "--listen-only",
                    "--listen",
                    "0.1",
                ]
            )
            == 1
        )
    finally:
        node.close()
    assert node.heard == [] and "no ABH3 found" in capsys.readouterr().out


def test_traffic_of_another_host_is_told_apart() -> None:
    f = Findings(host=2)
    f.observe(ids.request_id(9, 4), frames.encode_request(frames.PGN_DP0))  # host 4 asks
    f.observe(ids.dp0_command_id(9, 4), frames.encode_dp0_command(100, 0, 0x101))
    f.observe(ids.dp0_reply_id(9, 4), frames.encode_dp0_reply_2023(100, 0, 0x80000101))
    f.finish()
    assert set(f.drives) == {9} and f.drives[9].hosts == {4} and f.other_hosts == {4}
    assert f.drives[9].protocol == "2023"


@pytest.mark.wallclock
def test_a_bus_that_cannot_open_is_a_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["scan", "--interface", "wacousb", "--channel", "/nonexistent/ttyACM0"]) == 1
    err = capsys.readouterr().err
    assert "cannot open" in err and "Traceback" not in err


@pytest.mark.wallclock
def test_scan_through_the_makers_adapter(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    emu = AdapterEmulator(tmp_path / "ttyACM0", "scan-usb")
    node = SimNode("scan-usb", SimConfig(reply_latency_ms=0.0), {7: FIVE[7], 253: FIVE[253]})
    try:
        assert main(["scan", "--interface", "wacousb", "--channel", str(emu.link)]) == 0
    finally:
        node.close()
        emu.close()
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split()[1:4] for line in out.splitlines()[1:3]}
    assert rows == {"7": ["2023", "0", "motor"], "253": ["2021", "5", "travel"]}
    assert emu.bad == [] and all(ids.CanId.from_int(i).pf == ids.PF_REQUEST for i in node.heard)


@pytest.mark.wallclock
def test_an_empty_virtual_bus_says_it_reaches_only_this_process(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["scan", "--interface", "virtual", "--channel", "scan-nobody"]) == 1
    out = capsys.readouterr().out
    assert "python-can's virtual bus reaches only this process" in out
    assert "`abh3 simulate` puts them on udp_multicast" in out
