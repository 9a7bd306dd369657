"""The key help, generated from the bindings: what is bound is what is listed."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from textual.binding import Binding
from textual.keys import format_key

from abh3_supervisor.clients.tui.hold import FIRST_REPEAT_S, TICK_S

WIDTH = 10
TAP_S = FIRST_REPEAT_S + TICK_S  # an arrow pressed once drives this long


def key_name(key: str) -> str:
    """A key as an operator reads it: ``?`` not ``question_mark``, ``+`` not ``plus``."""
    return {"space": "space", "escape": "Esc"}.get(key) or format_key(key)


def help_lines(
    bindings: Iterable[Binding], plugin_keys: Mapping[str, Mapping[str, str]]
) -> list[str]:
    """One line per action (its keys joined), then each input plugin's forwarded keys."""
    by_action: dict[str, tuple[list[str], str]] = {}
    for b in bindings:
        keys, text = by_action.setdefault(b.action, ([], b.tooltip or b.description))
        keys += [key_name(k.strip()) for k in b.key.split(",")]
    lines = [
        "Keys, on every screen. Esc closes this help, a question (= no)",
        "or the command line. The selected unit is marked ▶ (n, p).",
        "ctrl+e is the E-STOP everywhere: on every tab, page and question",
        "and in every input line; e is the E-STOP everywhere but in an",
        "input line, where every printable key is text (commands are",
        "case-insensitive: vel 50 0). The e-stop closes every question",
        "and page, so its outcome is in sight. A held arrow drives while",
        f"the terminal repeats it (a tap: {TAP_S:.2g} s); a robot moves only",
        "while every drive of it reports SERVO and START on (o switches the",
        "selected unit's robot on, asked; the overview says why it is not",
        "ready, naming the drive). ctrl+c stops the arrows' drive and",
        "asks to quit, from every question, page and input line too.",
        "",
    ]
    for keys, text in by_action.values():
        lines.append(f"  {', '.join(keys):<{WIDTH}} {text}")
    for plugin, forwarded in plugin_keys.items():
        lines += ["", f"Plugin {plugin}: the TUI hands it these keys (its own win)"]
        for key, text in forwarded.items():
            lines.append(f"  {key_name(key) if key != ' ' else 'space':<{WIDTH}} {text}")
    return lines
