"""This process's CPU cgroup, read from /proc (runtime/cgroups.py), on fake hierarchies."""

from __future__ import annotations

from pathlib import Path

import pytest

from abh3_supervisor.runtime import cgroups
from abh3_supervisor.runtime.cgroups import Throttling, cpu_dir


def hierarchy(tmp_path: Path, mounts: str, own: str, *dirs: str) -> None:
    for d in dirs:
        (tmp_path / d).mkdir(parents=True)
    (tmp_path / "mounts").write_text(mounts.replace("ROOT", str(tmp_path)))
    (tmp_path / "cgroup").write_text(own)


@pytest.fixture(autouse=True)
def fake_proc(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cgroups, "MOUNTS", tmp_path / "mounts")
    monkeypatch.setattr(cgroups, "OWN", tmp_path / "cgroup")


V1 = "cgroup ROOT/cpu cgroup rw,relatime,cpu 0 0\ncgroup ROOT/mem cgroup rw,memory 0 0\n"
V2 = "cgroup2 ROOT/unified cgroup2 rw,relatime 0 0\n"


def test_v1_s_cpu_hierarchy_wins_on_a_hybrid_system(tmp_path: Path) -> None:
    hierarchy(tmp_path, V1 + V2, "4:memory:/m\n1:cpu:/limited\n0::/other\n", "cpu/limited")
    assert cpu_dir() == tmp_path / "cpu" / "limited"


def test_the_unified_hierarchy_where_there_is_no_v1_cpu(tmp_path: Path) -> None:
    hierarchy(tmp_path, V2, "0::/robot.slice/abh3.service\n", "unified/robot.slice/abh3.service")
    assert cpu_dir() == tmp_path / "unified" / "robot.slice" / "abh3.service"


@pytest.mark.parametrize(
    ("mounts", "own"),
    [
        ("proc /proc proc rw 0 0\n", "0::/\n"),  # no cgroups mounted
        (V1, "1:cpu:/gone\n"),  # a directory that is not there
        (V1, "not a cgroup line\n"),
    ],
)
def test_none_where_it_cannot_be_found(tmp_path: Path, mounts: str, own: str) -> None:
    hierarchy(tmp_path, mounts, own)
    assert cpu_dir() is None


def test_held_says_whether_the_quota_held_the_process_back_since_last_asked(
    tmp_path: Path,
) -> None:
    stat = tmp_path / "cpu.stat"
    stat.write_text("nr_periods 10\nnr_throttled 2\nthrottled_time 5\n")
    throttling = Throttling(tmp_path)
    assert not throttling.held()  # what came before it was made is not news
    stat.write_text("nr_periods 20\nnr_throttled 3\nthrottled_time 9\n")
    assert throttling.held()
    assert not throttling.held()  # said once
    stat.unlink()
    assert not throttling.held()  # gone: never again
    assert not Throttling(None).held()  # no cgroup at all
