"""Plugin sections are checked by `abh3 check` exactly as `abh3 run` checks them."""

from __future__ import annotations

from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

from abh3_supervisor.clients.cli import main
from abh3_supervisor.config import parse_config
from abh3_supervisor.config.source import Section
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.plugin_host import host as plugin_host
from abh3_supervisor.plugin_host.hookspecs import hookimpl
from abh3_supervisor.plugin_host.host import PluginHost
from tests.support.rig import TWO_UNITS


def problems(plugins: str) -> list[str]:
    cfg = parse_config(TWO_UNITS + "plugins:\n" + plugins, "p.yaml")
    with pytest.raises(ConfigError) as info:
        PluginHost(cfg)
    return info.value.problems


@pytest.mark.parametrize("plugin", ["keyboard", "joystick"])
def test_inputs_may_only_name_declared_units(plugin: str) -> None:
    assert problems(f"  {plugin}: {{units: [left, base]}}\n") == [
        f"p.yaml:9: plugins.{plugin}.units[1]: no robot or unit named 'base' (units: left, right)"
    ]


def test_csv_refuses_a_folder_or_a_place_it_cannot_write(tmp_path: Path) -> None:
    assert problems(f"  csv: {{path: {tmp_path}}}\n") == [
        f"p.yaml:9: plugins.csv.path: '{tmp_path}': is a folder: name a file in it"
    ]
    (tmp_path / "file").write_text("")
    found = problems(f"  csv: {{path: {tmp_path}/file/x.csv}}\n")
    assert found == [
        f"p.yaml:9: plugins.csv.path: '{tmp_path}/file/x.csv': '{tmp_path}/file' is not a folder"
    ]
    found = problems("  csv: {path: /proc/abh3/x.csv}\n")
    assert "cannot create a file in '/proc'" in found[0]


def test_csv_may_write_into_folders_it_will_create_and_check_writes_nothing(
    tmp_path: Path,
) -> None:
    target = tmp_path / "logs" / "{unit}" / "x.csv"
    PluginHost(parse_config(TWO_UNITS + f"plugins:\n  csv: {{path: '{target}'}}\n", "p.yaml"))
    assert list(tmp_path.iterdir()) == []


class Careless:
    """Its abh3_configure fails with something other than its section's errors."""

    @hookimpl
    def abh3_configure(self, section: Section) -> None:
        int(section.data["level"])


@pytest.fixture
def careless(monkeypatch: pytest.MonkeyPatch) -> None:
    entry = EntryPoint("careless", f"{__name__}:Careless", plugin_host.GROUP)
    installed = plugin_host.installed()
    monkeypatch.setattr(plugin_host, "installed", lambda: {**installed, "careless": entry})


@pytest.mark.wallclock
@pytest.mark.usefixtures("careless")
@pytest.mark.parametrize("command", ["check", "run"])
def test_a_plugin_failing_to_read_its_settings_is_a_config_error(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text(TWO_UNITS + "plugins:\n  careless: {level: high}\n")
    args = [command, str(cfg)] + (["--headless", "--duration", "1"] if command == "run" else [])
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err == (
        f"error: {cfg}:9: plugins.careless: plugin 'careless' cannot use these settings: "
        "ValueError(\"invalid literal for int() with base 10: 'high'\")\n"
    )
