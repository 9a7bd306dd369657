"""YAML with positions: every value keeps the line it came from, for error messages."""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

import yaml

from abh3_supervisor.errors import ConfigError

Path = tuple[str | int, ...]
T = TypeVar("T")


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

    def line(self, path: Path) -> int:
        while path not in self.lines and path:
            path = path[:-1]
        return self.lines.get(path, 1)

    def error(self, path: Path, message: str) -> None:
        self.problems.append(f"{self.file}:{self.line(path)}: {dotted(path)}: {message}")

    def raise_if_problems(self) -> None:
        if self.problems:
            raise ConfigError(self.problems)


def load_source(file: str, text: str) -> Source:
    """Parse YAML keeping line numbers; syntax errors and duplicate keys are reported."""
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else 1
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError([f"{file}:{line}: invalid YAML: {problem}"]) from exc
    src = Source(file, None)
    loader = yaml.SafeLoader("")
    src.data = {} if node is None else _construct(node, (), src, loader)
    return src


def _construct(node: yaml.Node, path: Path, src: Source, loader: yaml.SafeLoader) -> Any:
    src.lines[path] = node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        out: dict[Any, Any] = {}
        for key_node, value_node in node.value:
            key = loader.construct_object(key_node)  # scalar keys only
            if key in out:
                src.lines[(*path, str(key))] = key_node.start_mark.line + 1
                src.error((*path, str(key)), "duplicate key (the later one would win silently)")
            out[key] = _construct(value_node, (*path, str(key)), src, loader)
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_construct(item, (*path, i), src, loader) for i, item in enumerate(node.value)]
    return loader.construct_object(node)


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

    def only(self, allowed: set[str]) -> None:
        """Report every key not in ``allowed``, with a did-you-mean when one is close."""
        for key in self.data:
            if key not in allowed:
                hint = difflib.get_close_matches(str(key), sorted(allowed), n=1)
                did = f"; did you mean '{hint[0]}'?" if hint else ""
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
                return f"expected an integer {lo}–{hi}, got {_kind(v)} {v!r}"
            return None if lo <= v <= hi else f"{v} is out of range (allowed {lo}–{hi})"

        return self._get(key, default, check)

    def number(
        self, key: str, default: float, lo: float, hi: float, *, lo_open: bool = False
    ) -> float:
        allowed = f"more than {lo:g}, up to {hi:g}" if lo_open else f"{lo:g}–{hi:g}"

        def check(v: Any) -> str | None:
            if isinstance(v, bool) or not isinstance(v, int | float):
                return f"expected a number ({allowed}), got {_kind(v)} {v!r}"
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

    def choice(self, key: str, default: str, choices: list[str]) -> str:
        def check(v: Any) -> str | None:
            return None if str(v) in choices else f"{v!r} is not one of: {', '.join(choices)}"

        return str(self._get(key, default, check))


def _kind(value: Any) -> str:
    return {dict: "a mapping", list: "a list", str: "a string", type(None): "nothing"}.get(
        type(value), type(value).__name__
    )
