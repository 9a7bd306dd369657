"""What docs/plugins.md (and the public API's docstring) tell a plugin author is read from
the code: every public name, every feed call and section helper with its parameters, the
host's keys, the records' field types, `abh3 plugins --json`'s fields, the harness's
signatures and `wait_for`'s timeout, what a failing `abh3_stop` does to the exit code
(issue 53). And docs/architecture.md stays a page a newcomer reads in ten minutes."""

from __future__ import annotations

import dataclasses
import inspect
import re
from pathlib import Path

from abh3_supervisor import plugin_api, plugin_testing
from abh3_supervisor.clients.plugins import listing
from abh3_supervisor.config import schema
from abh3_supervisor.config.source import Section
from abh3_supervisor.plugin_host import host, validate
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.runtime import stopping

ROOT = Path(__file__).resolve().parent.parent
GUIDE = (ROOT / "docs" / "plugins.md").read_text(encoding="utf-8")
FLAT = re.sub(r"\s+", " ", GUIDE)  # a claim may wrap
NUMBERS = {3: "Three", 4: "Four", 5: "Five", 6: "Six"}


def section(title: str) -> str:
    """The text under the heading ``title`` up to the next heading of its level or above
    (code blocks left out: their comments are no headings)."""
    text = re.sub(r"^```.*?^```$", "", GUIDE, flags=re.M | re.S)
    found = re.search(rf"^(#+) {re.escape(title)}\n", text, re.M)
    assert found, f"docs/plugins.md has no heading {title!r}"
    rest = text[found.end() :]
    end = re.search(rf"^#{{1,{len(found.group(1))}}} ", rest, re.M)
    return rest if end is None else rest[: end.start()]


def public(cls: type) -> dict[str, inspect.Signature]:
    """``cls``'s public methods and their signatures (``self`` left out)."""
    out = {}
    for name, fn in inspect.getmembers(cls, inspect.isfunction):
        if not name.startswith("_"):
            sig = inspect.signature(fn)
            out[name] = sig.replace(parameters=list(sig.parameters.values())[1:])
    return out


def documented_params(call: str) -> list[str]:
    """The parameter names a documented call shows: ``number(key, default: float, *,
    lo_open=False) -> float`` → ``['key', 'default', 'lo_open']``."""
    inside = call.split("(", 1)[1].rsplit(")", 1)[0]
    inside = re.sub(r"\[[^\]]*\]", "", inside)  # tuple[str, ...]: no commas of its own
    names = [p.split(":")[0].split("=")[0].strip() for p in inside.split(",")]
    return [n for n in names if n and n != "*"]


def test_every_public_name_of_the_api_is_in_the_guides_table() -> None:
    table = section("The public API")
    named = set(re.findall(r"`(\w+)`", table))
    missing = sorted(set(plugin_api.__all__) - named)
    assert not missing, f"docs/plugins.md's public API table lacks {missing}"


def test_every_feed_call_is_documented_with_its_parameters() -> None:
    """A call of the bus loop's (its docstring begins "On the loop") is named as one a
    plugin must not call; every other one has its row, with the code's parameters."""
    calls = public(InputFeed)
    loop_only = {n for n in calls if (getattr(InputFeed, n).__doc__ or "").startswith("On the")}
    assert {"hold", "alive"} <= loop_only  # the reader works
    rows = dict(re.findall(r"^\| `feed\.(\w+)(\([^`]*\))[^`]*` \|", GUIDE, re.M))
    for name, sig in calls.items():
        if name in loop_only:
            continue
        assert name in rows, f"docs/plugins.md: no row for feed.{name}"
        assert documented_params(rows[name]) == list(sig.parameters), f"feed.{name}{sig}"
    assert not set(rows) - set(calls), f"documented, not in InputFeed: {set(rows) - set(calls)}"
    words = " ".join(f"`{n}`" for n in sorted(loop_only))
    said = re.search(r"`InputFeed` has \w+ more methods, ([^:]*):", FLAT)
    assert said and sorted(re.findall(r"`(\w+)`", said.group(1))) == sorted(loop_only), words
    docstring = re.sub(r"\s+", " ", plugin_api.__doc__ or "")
    for name in calls:  # the API's own docstring names each too
        assert f"``{name}" in docstring, f"plugin_api's docstring does not name feed.{name}"


def test_every_section_helper_is_documented_with_its_parameters() -> None:
    calls = public(Section)
    assert {"choice", "strings", "sub", "has", "output_path"} <= set(calls)
    rows = {
        name: f"({args})"
        for name, args in re.findall(r"^\| `(\w+)\(([^`]*)\)[^`]*` \|", GUIDE, re.M)
        if name in calls
    }
    missing = sorted(set(calls) - set(rows))
    assert not missing, f"docs/plugins.md's Section table lacks {missing}"
    for name, sig in calls.items():
        assert documented_params(rows[name]) == list(sig.parameters), f"{name}{sig}"


def test_the_host_keys_are_the_codes_and_every_mention_names_them_all() -> None:
    keys = set(validate.HOST_KEYS)
    assert keys == set(schema.HOST_KEYS), "the host's keys: plugin_host and the schema differ"
    count = NUMBERS[len(keys)]
    assert f"{count} keys are the host's" in FLAT
    elsewhere = FLAT.lower().replace(f"{count.lower()} keys are the host's", "")
    for word in NUMBERS.values():  # no other count of them anywhere ("three" was one)
        assert not re.search(rf"\b{word.lower()} (of the )?(host's )?keys\b", elsewhere), word
    paragraphs = [p for p in re.split(r"\n\s*\n", GUIDE) if "`critical`" in p]
    assert len(paragraphs) >= 3  # the reader works
    for paragraph in paragraphs:
        named = set(re.findall(r"`(\w+)`", paragraph))
        if "`on_error`" in paragraph:
            assert keys <= named, f"names some of the host's keys, not all:\n{paragraph}"
    docstring = re.sub(r"\s+", " ", plugin_api.__doc__ or "")
    listed = re.search(r"The host's keys[^:]*: ([^.]*)\.", docstring)
    assert listed and set(re.findall(r"``(\w+)``", listed.group(1))) == keys


def test_the_records_fields_are_written_with_their_types() -> None:
    for record in (plugin_api.OwnerChange, plugin_api.EstopChange):
        fields = ", ".join(f"{f.name}: {f.type}" for f in dataclasses.fields(record))
        assert f"`{record.__name__}({fields})`" in FLAT.replace("\\|", "|"), record


def test_the_json_listing_has_the_fields_the_guide_lists(tmp_path: Path) -> None:
    tools = section("Tools: listing, checking, the template, testing")
    table = tools.split("`--json` prints one object", 1)[1].split("\n\n", 2)
    said_top = set(re.findall(r"`(\w+)`", table[0]))
    rows = set(re.findall(r"^\| `(\w+)`(?:, `(\w+)`)? \|", table[1], re.M))
    fields = {f for row in rows for f in row if f}
    config = tmp_path / "c.yaml"
    config.write_text(
        "buses:\n  b: {interface: virtual, channel: x, simulate: true}\n"
        "units:\n  - {name: left, abh3_id: 1}\nplugins:\n  nope: {}\n"
    )
    data = listing(config)
    assert set(data) <= said_top
    installed = [p for p in data["plugins"] if p["name"] != "nope"]
    assert installed and all(set(p) == fields for p in installed)
    absent = next(p for p in data["plugins"] if p["name"] == "nope")
    only = re.search(r"not installed is listed with (.*?) only", re.sub(r"\s+", " ", tools))
    named = re.sub(r"\([^)]*\)", "", only.group(1)) if only else ""  # not the values
    assert set(re.findall(r"`(\w+)`", named)) == set(absent)


def test_the_harness_is_documented_with_its_defaults() -> None:
    for fn in (plugin_testing.run_with_plugin, plugin_testing.PluginRun.wait_for):
        sig = inspect.signature(fn)
        shown = ", ".join(
            p.name if p.default is inspect.Parameter.empty else f"{p.name}={p.default!r}"
            for p in sig.parameters.values()
            if p.name != "self"
        ).replace("'", '"')
        assert f"`{fn.__name__}({shown})`" in FLAT, f"{fn.__name__}({shown})"


def test_a_failing_abh3_stop_is_said_as_the_code_does_it() -> None:
    hooks = re.sub(r"\s+", " ", section("`abh3_stop`"))
    assert f"within {host.STOP_DEADLINE_S:g} s" in hooks
    assert f"exit code {stopping.EXIT_RECORDING_FAILED}" in hooks
    assert (stopping.EXIT_FAILED, stopping.EXIT_STOP_UNCONFIRMED) == (1, 3)
    assert "unless 1 or 3 apply" in hooks and "changes no exit code" in hooks
    table = section("Failure policy")
    codes = re.findall(r"^\| (\d) \|", table, re.M)
    assert codes == [
        "0",
        str(stopping.EXIT_FAILED),
        str(stopping.EXIT_STOP_UNCONFIRMED),
        str(stopping.EXIT_RECORDING_FAILED),
        str(stopping.EXIT_PLUGIN_DISABLED),
    ]


def test_the_architecture_page_reads_in_ten_minutes() -> None:
    """Issue 53: under about 3,000 words (`wc -w`), no paragraph a wall of text."""
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    assert len(text.split()) < 3200
    blocks = re.split(r"\n\s*\n|\n(?=- |\d+\. )", text)  # paragraphs and list items
    prose = [p for p in blocks if not p.lstrip().startswith(("|", "```"))]
    longest = max(prose, key=lambda p: len(p.split()))
    assert len(longest.split()) < 250, longest[:200]


def test_no_doc_says_the_tests_without_real_time_take_seconds() -> None:
    """Issue 53: "the fake-clock core runs in seconds" was false (minutes: docs/testing.md
    says what was measured, and how)."""
    for doc in (ROOT / "README.md", ROOT / "docs" / "testing.md"):
        text = re.sub(r"\s+", " ", doc.read_text(encoding="utf-8"))
        for said in re.finditer(r'"not wallclock"', text):
            after = text[said.end() : said.end() + 120]
            assert not re.search(r"\bin seconds\b|\d+ to \d+ s\b", after), f"{doc.name}: {after}"
    testing = (ROOT / "docs" / "testing.md").read_text(encoding="utf-8")
    assert '    .venv/bin/python -m pytest -m "not wallclock" -q -p no:randomly\n' in testing
