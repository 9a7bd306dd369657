"""YAML with positions: every value keeps the line it came from, for error messages.

The loader is safe on any file: its size, nesting depth and number of values (aliases
expanded) are bounded, the text must be UTF-8, and only plain YAML values are accepted
(no custom tags, no merge keys, no mappings or lists as keys). Every refusal names the
file and line; the limits are documented in docs/configuration.md.
"""

from __future__ import annotations

import codecs
import datetime
import math
import os
import re
import tempfile
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Any, TypeVar

import yaml

from abh3_supervisor.errors import ConfigError, did_you_mean

Path = tuple[str | int, ...]
T = TypeVar("T")

# Four full buses (4 × 254 drives) written out key by key are about 250 KiB; at this
# limit the worst file still loads in about a second, and a wrong path (a log, a
# device) is refused at once
MAX_BYTES = 512 << 10
MAX_DEPTH = 32  # ours nests 4 deep, plugin sections a few more
MAX_VALUES = 100_000  # after alias expansion: bounds memory and time (billion laughs)
# libyaml when built in: ~10× faster, so even a file at MAX_BYTES loads in about a second
_LOADER: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_CORE = "tag:yaml.org,2002:"
SCALAR_TAGS = {_CORE + t for t in ("str", "int", "float", "bool", "null", "timestamp")}
MERGE_TAG = _CORE + "merge"
# YAML 1.1 reads 1e3 as text, and 1.0e3 too: its floats need a dot and a signed exponent
EXPONENT_ONLY = re.compile(r"^[-+]?(?:\d+\.?\d*|\.\d+)[eE][-+]?\d+$")


def dotted(path: Path) -> str:
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
    return out or "(top level)"


@dataclass
class Source:
    """A parsed document: plain values plus the line of each path; collects problems."""

    file: str
    data: Any
    lines: dict[Path, int] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    # the units the document declares, once known: plugin sections may name only these
    unit_names: tuple[str, ...] = ()
    # the files plugins will write ({unit} unexpanded), each with where it is set
    # (file:line: key), so a --record onto one of them is refused before anything opens
    outputs: list[tuple[str, str]] = field(default_factory=list)

    def line(self, path: Path) -> int:
        while path not in self.lines and path:
            path = path[:-1]
        return self.lines.get(path, 1)

    def error(self, path: Path, message: str, line: int | None = None) -> None:
        where = self.line(path) if line is None else line
        self.problems.append(f"{self.file}:{where}: {dotted(path)}: {message}")

    def raise_if_problems(self) -> None:
        if self.problems:
            raise ConfigError(self.problems)


def read_text(path: str | os.PathLike[str]) -> str:
    """The file as text: at most MAX_BYTES, UTF-8 (a BOM is fine), else a ConfigError."""
    file = str(path)
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_BYTES + 1)  # never more: /dev/zero or a huge log is refused
    except OSError as exc:
        raise ConfigError([f"{file}: cannot read configuration: {exc.strerror or exc}"]) from exc
    if len(raw) > MAX_BYTES:
        raise ConfigError(
            [
                f"{file}:1: file: larger than {MAX_BYTES >> 10} KiB, not a configuration "
                "(is this the right file?)"
            ]
        )
    return decode_text(file, raw)


def decode_text(file: str, raw: bytes) -> str:
    raw = raw.removeprefix(codecs.BOM_UTF8)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        column = exc.start - raw.rfind(b"\n", 0, exc.start)
        raise ConfigError(
            [
                f"{file}:{line}: encoding: byte 0x{raw[exc.start]:02X} in column {column} is "
                "not UTF-8 (save the file as UTF-8)"
            ]
        ) from None


def load_source(file: str, text: str) -> Source:
    """Parse YAML keeping line numbers; syntax errors and duplicate keys are reported."""
    try:
        _check_depth(file, text)
        node = yaml.compose(text, Loader=_LOADER)
    except yaml.YAMLError as exc:
        line, problem = _syntax_error(exc, text)
        raise ConfigError([f"{file}:{line}: invalid YAML: {problem}"]) from None
    src = Source(file, None)
    src.data = {} if node is None else _Builder(src).value(node, ())
    return src


def _check_depth(file: str, text: str) -> None:
    """Refuse deep nesting from the event stream, before anything recurses over it."""
    depth = 0
    for event in yaml.parse(text, Loader=_LOADER):
        if isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_DEPTH:
                line = event.start_mark.line + 1 if event.start_mark else 1
                raise ConfigError(
                    [
                        f"{file}:{line}: nesting: more than {MAX_DEPTH} "
                        "levels of mappings and lists (a configuration needs a few)"
                    ]
                )
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1


def _syntax_error(exc: yaml.YAMLError, text: str) -> tuple[int, str]:
    if isinstance(exc, yaml.reader.ReaderError):  # a control character: an offset, no mark
        # libyaml counts UTF-8 bytes, the pure-Python reader characters
        if _LOADER is yaml.SafeLoader:
            newlines = text.count("\n", 0, exc.position)
        else:
            newlines = text.encode().count(b"\n", 0, exc.position)
        return newlines + 1, f"character {exc.character:#04x} is not allowed (control character)"
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    last = text.count("\n", 0, len(text.rstrip("\n"))) + 1  # libyaml may point past it
    return (min(mark.line + 1, last) if mark is not None else 1), problem


class _Builder:
    """Plain values from composed nodes, bounded: aliases count each time they expand."""

    def __init__(self, src: Source) -> None:
        self.src = src
        self.loader = yaml.SafeLoader("")
        self.count = 0
        self.inside: set[int] = set()  # nodes being built: meeting one again is a cycle

    def value(self, node: yaml.Node, path: Path) -> Any:
        self.src.lines[path] = node.start_mark.line + 1
        self.count += 1
        if self.count > MAX_VALUES:
            self._fatal(path, f"more than {MAX_VALUES} values once aliases are expanded")
        if id(node) in self.inside:
            self._fatal(path, "this alias refers to the value it is inside of (a cycle)")
        self.inside.add(id(node))
        try:
            if isinstance(node, yaml.MappingNode):
                self._plain(node, path, (_CORE + "map",))
                return self._mapping(node, path)
            if isinstance(node, yaml.SequenceNode):
                self._plain(node, path, (_CORE + "seq",))
                return [self.value(item, (*path, i)) for i, item in enumerate(node.value)]
            return self._scalar(node, path)
        finally:
            self.inside.discard(id(node))

    def _fatal(self, path: Path, message: str) -> None:
        raise ConfigError([f"{self.src.file}:{self.src.line(path)}: {dotted(path)}: {message}"])

    def _plain(self, node: yaml.Node, path: Path, allowed: Collection[str]) -> bool:
        if node.tag in allowed:
            return True
        message = f"the tag {_short(node.tag)} is not allowed: write a plain value"
        self.src.error(path, message, node.start_mark.line + 1)
        return False

    def _mapping(self, node: yaml.MappingNode, path: Path) -> dict[Any, Any]:
        out: dict[Any, Any] = {}
        for key_node, value_node in node.value:
            line = key_node.start_mark.line + 1
            if not isinstance(key_node, yaml.ScalarNode):
                kind = "a mapping" if isinstance(key_node, yaml.MappingNode) else "a list"
                self.src.error(path, f"a key must be a plain name, not {kind}", line)
                continue
            if key_node.tag == MERGE_TAG:
                self.src.error(
                    (*path, "<<"), "merge keys are not supported: write the keys out", line
                )
                continue
            key = self._scalar(key_node, (*path, str(key_node.value) or "(key)"))
            here = (*path, str(key))
            if key in out:
                self.src.lines[here] = line
                self.src.error(here, "duplicate key (the later one would win silently)")
            out[key] = self.value(value_node, here)
        return out

    def _scalar(self, node: yaml.Node, path: Path) -> Any:
        if not self._plain(node, path, SCALAR_TAGS):
            return str(node.value)
        try:
            return self.loader.construct_object(node)
        except (yaml.YAMLError, ValueError, OverflowError) as exc:  # e.g. a 13th month
            self.src.error(path, f"cannot read {node.value!r}: {exc}", node.start_mark.line + 1)
            return str(node.value)


def _short(tag: str) -> str:
    return "!!" + tag.removeprefix(_CORE) if tag.startswith(_CORE) else tag


class Section:
    """Typed, validating access to one mapping of a :class:`Source`."""

    def __init__(self, src: Source, path: Path, data: Any, allowed: set[str] | None) -> None:
        """``allowed`` None: the keys are checked later with :meth:`only` (plugin sections)."""
        self.src, self.path = src, path
        if data is None:
            data = {}
        if not isinstance(data, dict):
            src.error(path, f"expected a mapping, got {_kind(data)}")
            data = {}
        self.data: dict[Any, Any] = data
        if allowed is not None:
            self.only(allowed)

    def only(self, allowed: set[str], said: Collection[str] = ()) -> None:
        """Report every key not in ``allowed``, with a did-you-mean when one is close;
        keys in ``said`` were reported already, with a message of their own."""
        for key in self.data:
            if key not in allowed and key not in said:
                did = did_you_mean(str(key), sorted(allowed))
                self.src.error(
                    (*self.path, str(key)),
                    f"unknown key{did} (allowed: {', '.join(sorted(allowed))})",
                )

    def has(self, key: str) -> bool:
        return key in self.data

    def error(self, key: str, message: str) -> None:
        self.src.error((*self.path, key), message)

    def sub(self, key: str, allowed: set[str] | None) -> Section:
        return Section(self.src, (*self.path, key), self.data.get(key), allowed)

    def items(self) -> Iterator[tuple[str, Any]]:
        yield from ((str(k), v) for k, v in self.data.items())

    def _get(self, key: str, default: T, check: Callable[[Any], str | None]) -> T:
        if key not in self.data:
            return default
        value = self.data[key]
        problem = check(value)
        if problem:
            self.error(key, problem)
            return default
        return value  # type: ignore[no-any-return]

    def integer(self, key: str, default: int, lo: int, hi: int) -> int:
        def check(v: Any) -> str | None:
            if isinstance(v, bool) or not isinstance(v, int):
                return f"expected an integer {lo}–{hi}, got {_kind(v)} {_shown(v)}"
            return None if lo <= v <= hi else f"{v} is out of range (allowed {lo}–{hi})"

        return self._get(key, default, check)

    def number(
        self, key: str, default: float, lo: float, hi: float, *, lo_open: bool = False
    ) -> float:
        allowed = f"more than {lo:g}, up to {hi:g}" if lo_open else f"{lo:g}–{hi:g}"

        def check(v: Any) -> str | None:
            if isinstance(v, str) and EXPONENT_ONLY.match(v):
                return (
                    f"YAML reads {v} as text: write it with a dot and a signed exponent, "
                    f"e.g. {_with_dot(v)}"
                )
            if isinstance(v, bool) or not isinstance(v, int | float):
                return f"expected a number ({allowed}), got {_kind(v)} {_shown(v)}"
            if not math.isfinite(v):
                return f"{v} is not a finite number"
            ok = (v > lo if lo_open else v >= lo) and v <= hi
            return None if ok else f"{v:g} is out of range (allowed {allowed})"

        return float(self._get(key, default, check))

    def boolean(self, key: str, default: bool) -> bool:
        return self._get(
            key,
            default,
            lambda v: None if isinstance(v, bool) else f"expected true or false, got {v!r}",
        )

    def text(self, key: str, default: str) -> str:
        return self._get(
            key,
            default,
            lambda v: (
                None if isinstance(v, str) and v else f"expected a non-empty string, got {v!r}"
            ),
        )

    def strings(self, key: str, default: tuple[str, ...]) -> tuple[str, ...]:
        def check(v: Any) -> str | None:
            if isinstance(v, list) and v and all(isinstance(x, str) and x for x in v):
                return None
            return f"expected a list of names, got {v!r}"

        value = self._get(key, default, check)
        return tuple(value)

    def units(self, key: str) -> tuple[str, ...]:
        """Names of units the document declares (an input's targets, for example)."""
        names = self.strings(key, ())
        for i, name in enumerate(names):
            if name not in self.src.unit_names:
                declared = ", ".join(self.src.unit_names) or "none"
                self.src.error((*self.path, key, i), f"no unit named {name!r} (units: {declared})")
        return names

    def output_path(self, key: str, default: str) -> str:
        """A file to write, checked now so `check` finds what `run` would fail on.

        ``{unit}`` in it stands for each unit's name. The file's nearest existing folder
        must take a new file (its missing folders are created at run time).
        """
        text = self.text(key, default)
        path = FsPath(text.replace("{unit}", "unit"))
        problem = _unwritable(path)
        if problem:
            self.error(key, f"{text!r}: {problem}")
        where = (*self.path, key)
        self.src.outputs.append((text, f"{self.src.file}:{self.src.line(where)}: {dotted(where)}"))
        return text

    def choice(self, key: str, default: str, choices: list[str]) -> str:
        def check(v: Any) -> str | None:
            return None if str(v) in choices else f"{v!r} is not one of: {', '.join(choices)}"

        return str(self._get(key, default, check))


def _kind(value: Any) -> str:
    if isinstance(value, datetime.date):  # YAML reads 2001-12-14 as a date
        return "a date"
    return {dict: "a mapping", list: "a list", str: "a string", type(None): "nothing"}.get(
        type(value), type(value).__name__
    )


def _with_dot(number: str) -> str:
    """``1e3`` → ``1.0e+3``, ``2.5E-3`` → ``2.5e-3``: what YAML 1.1 reads as a float."""
    mantissa, _, exponent = number.lower().partition("e")
    if "." not in mantissa:
        mantissa += ".0"
    return f"{mantissa}e{exponent if exponent[:1] in '+-' else '+' + exponent}"


def _unwritable(path: FsPath) -> str | None:
    if path.is_dir():
        return "is a folder: name a file in it"
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        return f"{str(folder)!r} is not a folder"
    try:  # permissions alone do not tell (root, read-only or virtual file systems)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        return f"cannot create a file in {str(folder)!r}: {exc.strerror or exc}"
    return None


def _shown(value: Any) -> str:
    return f"'{value}'" if isinstance(value, datetime.date) else repr(value)
