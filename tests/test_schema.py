"""`abh3 schema`: a JSON Schema every shipped configuration meets and broken ones fail.

The schema is what an editor checks as you type; `abh3 check` stays the full check. So:
every shipped file (configs/, the YAML in the docs) validates; every file of the
bad-config corpus that is wrong in itself (a type, a range, an unknown key, a name)
fails it; only mistakes that need the whole file (duplicates, timing rules, startup
commands, writable paths, the bus-load plan) may pass it. And the schema names exactly
the keys the loader and each plugin accept, so neither can drift from the other.
"""

from __future__ import annotations

import json
import re
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from abh3_supervisor.clients.cli import main
from abh3_supervisor.clients.schema import config_schema
from abh3_supervisor.config import parse, robots
from abh3_supervisor.config.parse import parse_config
from abh3_supervisor.plugin_host.hookspecs import hookimpl
from abh3_supervisor.plugin_host.host import GROUP, PluginHost, section_schemas

ROOT = Path(__file__).resolve().parent.parent
BAD = ROOT / "tests" / "data" / "bad-configs"
EXPECT: dict[str, dict[str, Any]] = json.loads((BAD / "expect.json").read_text())
# mistakes only the whole file shows (or PyYAML's loader hides: it keeps the last of two
# duplicate keys, reads UTF-16): the schema may let these pass, `abh3 check` never does
WHOLE_FILE = (
    "clash-",
    "dup-",
    "dupkey-",
    "encoding-utf16",
    "plugin-csv-path-",
    "plugin-joystick-unknown-unit",
    "plugin-keyboard-unknown-unit",
    "plugin-ros2-namespace-clash",
    "rates-",
    "runtime-",
    "startup-",
    "timing-",
)
# plugins the docs show how to write; not installed here
EXAMPLE_PLUGINS = {"my_plugin", "speed_summary", "jsonl", "script", "overspeed"}
MINIMAL = {
    "buses": {"can0": {"interface": "virtual", "simulate": True}},
    "units": [{"name": "base"}],
}


@pytest.fixture(scope="module")
def validator() -> jsonschema.protocols.Validator:
    schema = config_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def problems(validator: jsonschema.protocols.Validator, data: Any) -> list[str]:
    return [
        f"{'.'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(data)
    ]


@pytest.mark.parametrize("path", sorted((ROOT / "configs").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_config_validates(
    validator: jsonschema.protocols.Validator, path: Path
) -> None:
    assert problems(validator, yaml.safe_load(path.read_text())) == []


def doc_blocks() -> list[tuple[str, str]]:
    """Every ```yaml block of the docs: an abh3 file or a part of one. Another tool's YAML
    (ros2_control's controllers) is fenced ```yaml <tool>, which this leaves out."""
    docs = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return [
        (f"{p.relative_to(ROOT)}#{i}", block)
        for p in docs
        for i, block in enumerate(re.findall(r"```yaml\n(.*?)```", p.read_text(), re.S))
    ]


@pytest.mark.parametrize(("where", "block"), doc_blocks(), ids=[w for w, _ in doc_blocks()])
def test_every_yaml_example_in_the_docs_validates(
    validator: jsonschema.protocols.Validator, where: str, block: str
) -> None:
    data = yaml.safe_load(_dedent(block))
    for name in EXAMPLE_PLUGINS & set(data.get("plugins") or {}):
        del data["plugins"][name]
    assert problems(validator, {**MINIMAL, **data}) == []  # fragments: a minimal file around


def _dedent(block: str) -> str:
    indent = min(len(line) - len(line.lstrip()) for line in block.splitlines() if line.strip())
    return "\n".join(line[indent:] for line in block.splitlines())


def test_the_docs_show_yaml_to_check() -> None:
    assert len(doc_blocks()) >= 5


def loadable_bad_configs() -> list[tuple[str, Any]]:
    out = []
    for path in sorted(BAD.glob("*.yaml")):
        try:
            data = yaml.safe_load(path.read_bytes())
        except (yaml.YAMLError, ValueError, RecursionError):
            continue  # not a document an editor could check either: syntax, encoding
        out.append((path.name, data))
    return out


@pytest.mark.parametrize(
    ("name", "data"), loadable_bad_configs(), ids=[n for n, _ in loadable_bad_configs()]
)
def test_the_bad_config_corpus(
    validator: jsonschema.protocols.Validator, name: str, data: Any
) -> None:
    found = problems(validator, data)
    if EXPECT[name]["check"] == [0]:
        assert found == [], "a file `abh3 check` accepts must meet the schema"
    elif name.startswith("type-"):
        assert found, "a type error must fail the schema"
    elif not name.startswith(WHOLE_FILE):
        assert found, "wrong in itself: the schema must see it"


def test_the_corpus_still_holds_what_this_test_is_about() -> None:
    names = [name for name, _ in loadable_bad_configs()]
    assert sum(n.startswith("type-") for n in names) >= 14
    assert sum(n.startswith(("range-", "unknown-", "name-")) for n in names) >= 20


def test_the_schema_names_exactly_the_loaders_keys() -> None:
    props = config_schema()["properties"]
    assert set(props) == parse.TOP_KEYS
    bus = props["buses"]["additionalProperties"]["properties"]
    assert set(bus) == parse.BUS_KEYS
    sim = bus["simulate"]["anyOf"][1]["properties"]
    assert set(sim) == parse.SIM_KEYS
    unit = props["units"]["items"]["properties"]
    assert set(unit) == parse.UNIT_KEYS
    assert set(unit["broadcast"]["properties"]) == parse.BROADCAST_KEYS
    assert set(unit["geometry"]["properties"]) == parse.GEOMETRY_KEYS
    assert set(unit["limits"]["properties"]) == parse.LIMIT_KEYS
    assert set(unit["data_select"]["properties"]) == parse.SELECT_KEYS
    robot = props["robots"]["items"]["properties"]
    assert set(robot) == robots.ROBOT_KEYS
    assert set(robot["wheels"]["items"]["properties"]) == robots.WHEEL_KEYS
    assert set(robot["limits"]["properties"]) == robots.ROBOT_LIMIT_KEYS


@pytest.mark.parametrize("plugin", ["csv", "keyboard", "joystick", "ros2"])
def test_each_plugin_accepts_every_key_its_schema_names_at_its_default(
    plugin: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each key alone (with what else is required), at its schema's default, passes the
    plugin's own check as `abh3 check` runs it: the schema offers nothing it refuses."""
    monkeypatch.chdir(tmp_path)  # csv's default path must be writable
    schemas, _ = section_schemas()
    section_schema = schemas[plugin]
    assert section_schema is not None
    # what is required, or the first of the alternatives (keyboard: units or robot)
    first = section_schema.get("anyOf", [{}])[0].get("required", ())
    required = {k: ["base"] for k in (*section_schema.get("required", ()), *first)}
    for key, prop in section_schema["properties"].items():
        kind = prop.get("type")
        value = prop.get(
            "default", ["base"] if kind == "array" else "base" if kind == "string" else {}
        )
        text = yaml.safe_dump({**MINIMAL, "plugins": {plugin: {**required, key: value}}})
        PluginHost(parse_config(text))  # raises ConfigError listing any problem


def test_a_plugin_without_the_hook_gets_a_free_section_and_a_broken_one_a_warning(
    capsys: pytest.CaptureFixture[str],
) -> None:
    eps = {
        "quiet": EntryPoint("quiet", f"{__name__}:Quiet", GROUP),
        "broken": EntryPoint("broken", f"{__name__}:Broken", GROUP),
        "own": EntryPoint("own", f"{__name__}:Own", GROUP),
    }
    schemas, failed = section_schemas(eps)
    assert schemas == {"quiet": None, "own": {"type": "object"}}
    assert "schema is broken" in failed["broken"]


class Quiet:
    @hookimpl
    def abh3_configure(self) -> None:
        pass


class Broken:
    @hookimpl
    def abh3_config_schema(self) -> dict[str, Any]:
        raise RuntimeError("schema is broken")


class Own:
    @hookimpl
    def abh3_config_schema(self) -> dict[str, Any]:
        return {"type": "object"}


@pytest.mark.wallclock
def test_abh3_schema_prints_it_and_writes_it(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    assert main(["schema"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["$schema"].endswith("2020-12/schema")
    assert set(printed["properties"]["plugins"]["properties"]) >= {"csv", "ros2"}
    out = tmp_path / "abh3.schema.json"
    assert main(["schema", "--output", str(out)]) == 0
    assert json.loads(out.read_text()) == printed
    assert main(["schema", "--output", str(tmp_path)]) == 2  # a folder: said, no traceback
    assert "cannot write" in capsys.readouterr().err


def test_on_error_is_offered_in_every_plugin_section(
    validator: jsonschema.protocols.Validator,
) -> None:
    ok = {**MINIMAL, "plugins": {"csv": {"on_error": "stop"}}}
    assert problems(validator, ok) == []
    bad = {**MINIMAL, "plugins": {"csv": {"on_error": "ignore"}}}
    assert problems(validator, bad)
