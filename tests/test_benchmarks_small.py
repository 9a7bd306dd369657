"""Section 12, a small computer's budget: the cgroup it makes, the search for the largest
configuration that holds, the verdict, and (where root and a namespace allow) a short run
whose supervisor the cgroup really holds to its share."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from abh3_supervisor.runtime import cgroups, netns
from benchmarks import cgroup, small


def _mounts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, *lines: str, own: str) -> None:
    (tmp_path / "mounts").write_text("".join(f"{line}\n" for line in lines))
    (tmp_path / "cgroup").write_text(own)
    monkeypatch.setattr(cgroups, "MOUNTS", tmp_path / "mounts")  # read by the runtime's
    monkeypatch.setattr(cgroups, "OWN", tmp_path / "cgroup")


def test_a_v1_cpu_hierarchy_gets_quota_over_period(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """cgroup v1: the child is made in this process's own cpu cgroup; 10 % of a core is
    10 ms of every 100 ms."""
    root = tmp_path / "cpu"
    (root / "robot").mkdir(parents=True)
    _mounts(
        tmp_path,
        monkeypatch,
        f"cgroup {tmp_path / 'cpuacct'} cgroup rw,relatime,cpuacct 0 0",  # not "cpu"
        f"cgroup {root} cgroup rw,relatime,cpu 0 0",
        own="2:cpuacct:/\n1:cpu:/robot\n0::/\n",
    )
    assert cgroup.unavailable() is None
    with cgroup.CpuLimit(10, name="t") as limit:
        assert limit.version == 1 and limit.path == root / "robot" / "t"
        assert (limit.path / "cpu.cfs_quota_us").read_text() == "10000"
        assert (limit.path / "cpu.cfs_period_us").read_text() == "100000"
        limit.add(1234)
        assert (limit.path / "cgroup.procs").read_text() == "1234"


def test_a_v2_hierarchy_hands_the_cpu_controller_down_and_sets_cpu_max(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = tmp_path / "unified"
    root.mkdir()
    (root / "cgroup.controllers").write_text("cpuset cpu io memory pids\n")
    _mounts(tmp_path, monkeypatch, f"cgroup2 {root} cgroup2 rw,relatime 0 0", own="0::/\n")
    with cgroup.CpuLimit(5, name="t") as limit:
        assert limit.version == 2
        assert (root / "cgroup.subtree_control").read_text() == "+cpu"
        assert (root / "t" / "cpu.max").read_text() == "5000 100000"
        (root / "t" / "cpu.stat").write_text(
            "usage_usec 10\nnr_periods 40\nnr_throttled 10\nthrottled_usec 250000\n"
        )
        assert limit.throttled() == {"periods": 40, "throttled": 10, "throttled_s": 0.25}


def test_without_a_cpu_controller_it_says_why(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A hybrid machine whose v2 mount offers no cpu controller and no v1 cpu hierarchy:
    no cgroup, the reason said, and section 12 adds no row."""
    root = tmp_path / "unified"
    root.mkdir()
    (root / "cgroup.controllers").write_text("hugetlb\n")
    _mounts(tmp_path, monkeypatch, f"cgroup2 {root} cgroup2 rw 0 0", own="0::/\n")
    assert cgroup.unavailable() == "no cgroup hierarchy with the cpu controller is mounted"
    with pytest.raises(RuntimeError, match="no CPU cgroup"):
        cgroup.CpuLimit(10).__enter__()
    assert small.rows(1.0, 1) == []
    assert "section 12 skipped: no cgroup hierarchy" in capsys.readouterr().out


def test_a_share_outside_one_core_is_refused() -> None:
    for percent in (0, -5, 150):
        with pytest.raises(ValueError, match="share of one core"):
            cgroup.CpuLimit(percent)


def test_the_largest_count_that_holds_is_found_by_bisection() -> None:
    counts = small.SIZING_UNITS  # 1, 2, 4, 8, 16
    for limit, expected in ((5, 4), (0, 0), (100, 16), (1, 1), (8, 8)):
        tried: list[int] = []

        def holds(units: int, limit: int = limit, tried: list[int] = tried) -> bool:
            tried.append(units)
            return units <= limit

        assert small.largest(holds, counts) == expected
        assert len(tried) <= 3  # log2 of 5 counts, not every count


def test_a_configuration_holds_only_on_rate_jitter_and_no_timeouts() -> None:
    good = {"rate_error_percent": 0.5, "jitter_p99_ms": 4.9, "timeouts": 0.0}
    assert small.Run(4, 100, 10, good).holds
    for key, bad in (("rate_error_percent", 1.2), ("jitter_p99_ms", 5.1), ("timeouts", 1.0)):
        assert not small.Run(4, 100, 10, good | {key: bad}).holds


def test_sizing_leaves_out_what_no_can_bus_carries() -> None:
    """16 units at 200 Hz exceed even 1 Mbit/s: `abh3 run` refuses it, so no computer is
    sized for it; 8 at 200 Hz and 16 at 100 Hz fit."""
    assert not small.fits(16, 200)
    assert small.fits(8, 200) and small.fits(16, 100) and small.fits(4, 100)


@pytest.mark.wallclock
def test_the_supervisor_is_held_to_its_share(tmp_path: Path) -> None:
    """A short run at 10 % of a core: the supervisor's CPU over the window is the share
    (not more), the figures of a run come back, and the cgroup is gone afterwards."""
    why = cgroup.unavailable() or netns.unavailable()
    if why is not None:
        pytest.skip(f"section 12 needs a CPU cgroup and a network namespace: {why}")
    done = small.run(10, units=1, rate=50, seconds=1.5, bridge=small.bridge_available() is None)
    f = done.figures
    assert 0 < f["supervisor_cpu_percent"] <= 10 * 1.3  # the quota, one CFS slice of slack
    assert f["simulator_cpu_percent"] > 0 and f["timeouts"] >= 0
    assert f["rate_error_percent"] < 100  # the unit's commands were heard on the wire
    found = cgroup.parent()
    assert found is not None
    assert not (found[0] / f"abh3-small-{os.getpid()}").exists()


def test_a_start_that_does_not_fit_the_share_does_not_hold(tmp_path: Path) -> None:
    """At 5 % the bridge's start can outlast the plugin host's 5 s: such a run did not
    start, says why (the supervisor's error line), and repetitions count by majority."""
    log = tmp_path / "run.err"
    log.write_text(
        "10:00:00.1 INFO    plugins loaded: ros2\n"
        "error: plugin ros2 could not start (abh3_start): did not return within 5 s\n\n"
    )
    why = small._said(log)
    assert why == "error: plugin ros2 could not start (abh3_start): did not return within 5 s"
    figures = {"rate_error_percent": 0.1, "jitter_p99_ms": 1.0, "timeouts": 0.0}
    ok, other = small.Run(1, 50, 5, figures), small.Run(1, 50, 5, figures | {"jitter_p99_ms": 3.0})
    not_started = small.Run(1, 50, 5, {}, why=why)
    assert not not_started.holds
    assert small.median_run([not_started, ok, not_started]).why == why
    two = small.median_run([ok, not_started, other])
    assert two.holds and two.figures["jitter_p99_ms"] == 2.0  # the median of those that ran
