"""Errors that name the real cause when a bus cannot open (issue 21): an interface name
python-can does not know is a mistake in the file, found by `check`; a kernel without
SocketCAN is said to be one, not "is the interface up?"; `abh3 scan`, which has no file,
never suggests a key of one."""

from __future__ import annotations

import errno
import socket
from pathlib import Path
from typing import Any

import can
import pytest

from abh3_supervisor.clients.cli import main
from abh3_supervisor.config import BusConfig, parse_config
from abh3_supervisor.errors import BusOpenError, ConfigError
from abh3_supervisor.runtime.bus_runtime import open_bus, simulated

NO_AF_CAN = OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")
NO_DEVICE = OSError(errno.ENODEV, "No such device")


def refuse(monkeypatch: pytest.MonkeyPatch, exc: BaseException) -> None:
    """can.Bus raises ``exc``, as python-can's socketcan does on such a machine."""

    def bus(**kwargs: Any) -> can.BusABC:
        raise exc

    monkeypatch.setattr(can, "Bus", bus)


def socketcan(channel: str = "can0") -> BusConfig:
    return BusConfig(name="robot", interface="socketcan", channel=channel, bitrate=500_000)


# ---------------------------------------------------------------- unknown interfaces


@pytest.mark.parametrize(
    ("written", "suggested"), [("sockecan", "socketcan"), ("SocketCAN", "socketcan")]
)
@pytest.mark.parametrize("simulate", ["", ", simulate: true"])
def test_an_unknown_interface_is_a_config_error_with_a_did_you_mean(
    written: str, suggested: str, simulate: str
) -> None:
    text = f"buses:\n  robot: {{interface: {written}, channel: can0{simulate}}}\nunits: [{{name: u}}]\n"
    with pytest.raises(ConfigError) as info:
        parse_config(text, "r.yaml")
    (problem,) = info.value.problems
    assert problem.startswith(
        f"r.yaml:2: buses.robot.interface: python-can has no interface '{written}'; "
        f"did you mean '{suggested}'? (its interfaces: "
    )


def test_every_interface_python_can_knows_is_accepted_entry_points_too() -> None:
    assert "wacousb" in can.interfaces.VALID_INTERFACES  # ours, through its entry point
    for name in sorted(can.interfaces.VALID_INTERFACES):
        parse_config(f"buses: {{b: {{interface: {name}}}}}\nunits: [{{name: u}}]\n", "i.yaml")


def test_a_name_like_none_gets_no_suggestion() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config("buses: {b: {interface: zzzz}}\nunits: [{name: u}]\n", "z.yaml")
    (problem,) = info.value.problems
    assert "did you mean" not in problem and "python-can has no interface 'zzzz'" in problem


def test_a_configuration_built_in_code_is_refused_when_the_bus_opens() -> None:
    typo = BusConfig(name="robot", interface="sockecan")
    for opening in (open_bus, simulated):
        with pytest.raises(BusOpenError, match="did you mean 'socketcan'"):
            opening(typo)


@pytest.mark.wallclock
def test_scan_refuses_an_unknown_interface_as_a_command_line_mistake(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["scan", "--interface", "sockecan", "--channel", "can0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(
        "error: --interface sockecan: python-can has no interface 'sockecan'; "
        "did you mean 'socketcan'?"
    )
    assert "Traceback" not in err


# ---------------------------------------------------------------- no SocketCAN in the kernel

KERNEL_WITHOUT_SOCKETCAN = (
    "bus 'robot': cannot open socketcan channel 'can0': [Errno 97] Address family not "
    "supported by protocol: this kernel has no SocketCAN at all (no CAN address family, "
    "whatever the device): load it with `sudo modprobe can can_raw` (the kernel must be "
    "built with CONFIG_CAN), or use an interface that needs no SocketCAN, such as the drive "
    "maker's USB-CAN adapter (`interface: wacousb`, channel /dev/ttyACM0) or an slcan "
    "adapter (`interface: slcan`); or add `simulate: true` to the bus to run it on the "
    "simulator"
)


def test_errno_97_says_the_kernel_has_no_socketcan(monkeypatch: pytest.MonkeyPatch) -> None:
    refuse(monkeypatch, NO_AF_CAN)
    with pytest.raises(BusOpenError) as info:
        open_bus(socketcan())
    assert str(info.value) == KERNEL_WITHOUT_SOCKETCAN
    assert "interface up" not in str(info.value)


def test_errno_97_is_found_inside_what_python_can_wraps(monkeypatch: pytest.MonkeyPatch) -> None:
    try:
        raise can.CanInitializationError("could not create the socket") from NO_AF_CAN
    except can.CanInitializationError as wrapped:
        refuse(monkeypatch, wrapped)
    with pytest.raises(BusOpenError, match=r"no SocketCAN at all.*modprobe can can_raw"):
        open_bus(socketcan())


@pytest.mark.wallclock
def test_run_says_it_with_exit_1_before_any_drive(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    refuse(monkeypatch, NO_AF_CAN)
    path = tmp_path / "robot.yaml"
    path.write_text("buses:\n  robot: {interface: socketcan, channel: can0}\nunits: [{name: u}]\n")
    assert main(["run", str(path), "--headless", "--duration", "1"]) == 1
    err = capsys.readouterr().err
    assert f"error: {KERNEL_WITHOUT_SOCKETCAN}\n" in err and "Traceback" not in err


@pytest.mark.wallclock
def test_scan_says_it_without_naming_keys_of_a_file(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    refuse(monkeypatch, NO_AF_CAN)
    assert main(["scan", "--interface", "socketcan", "--channel", "can0"]) == 1
    err = capsys.readouterr().err
    assert "no SocketCAN at all" in err and "sudo modprobe can can_raw" in err
    assert "`--interface wacousb`" in err and "`--interface slcan`" in err
    assert "simulate" not in err and "interface:" not in err and "interface up" not in err


@pytest.mark.wallclock
def test_a_missing_device_keeps_its_hint_and_scan_names_no_yaml(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    refuse(monkeypatch, NO_DEVICE)
    with pytest.raises(BusOpenError) as info:
        open_bus(socketcan("can9"))
    assert str(info.value) == (
        "bus 'robot': cannot open socketcan channel 'can9': [Errno 19] No such device (is the "
        "interface up? e.g. `sudo ip link set can9 up type can bitrate 500000`; or add "
        "`simulate: true` to the bus to run it on the simulator)"
    )
    assert main(["scan", "--interface", "socketcan", "--channel", "can9"]) == 1
    err = capsys.readouterr().err
    assert "is the interface up?" in err and "simulate" not in err


def _kernel_lacks_af_can() -> bool:
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        return exc.errno == errno.EAFNOSUPPORT
    except AttributeError:  # not Linux: no AF_CAN in Python at all
        return False
    return False


@pytest.mark.wallclock
@pytest.mark.skipif(not _kernel_lacks_af_can(), reason="this kernel has SocketCAN")
def test_on_a_kernel_without_socketcan_python_can_itself_gives_errno_97() -> None:
    """Not injected: what python-can really raises here, so a change in it is noticed."""
    with pytest.raises(BusOpenError) as info:
        open_bus(socketcan())
    assert str(info.value) == KERNEL_WITHOUT_SOCKETCAN
