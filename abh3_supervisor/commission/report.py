"""The commissioning report: a JSON document for machines and a self-contained HTML page
for people (no scripts, fonts or style sheets from elsewhere: it opens offline and can
be attached to a delivery). Pure: both are strings built from the results."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from html import escape
from typing import Any

from abh3_supervisor.commission.model import AXES, Settings, Verdict
from abh3_supervisor.commission.robot import RobotResult
from abh3_supervisor.commission.svg import plot
from abh3_supervisor.commission.unit import UnitResult
from abh3_supervisor.commission.wheels import places
from abh3_supervisor.params import table


@dataclass(frozen=True, slots=True)
class Session:
    tool: str  # "abh3-supervisor 0.1.0"
    time: str  # ISO 8601, when the run began
    config_file: str
    yaml: str
    settings: Settings
    results: Mapping[str, UnitResult]
    ended: str | None = None  # why the session ended early
    stops: Mapping[str, str] | None = None  # unit → the stop's outcome at the end
    record: str | None = None
    robots: Mapping[str, RobotResult] | None = None  # the robot step's, per robot


def unit_json(name: str, r: UnitResult, stop: str | None) -> dict[str, Any]:
    cfg = r.cfg
    return {
        "unit": name,
        "verdict": r.verdict.value,
        "bus": cfg.bus,
        "abh3_id": cfg.abh3_id,
        "protocol": cfg.protocol.value,
        "velocity_model": cfg.velocity_model.value,
        "firmware": r.firmware,
        "ended": r.ended,
        "stop": stop,
        "checks": [c.to_json() for c in r.checks],
        "can_settings": r.settings_rows,
        "parameters": [
            {"address": f"0x{a:04X}", "name": table.label(a), "value": v}
            for a, v in r.params.items()
        ],
        "traces": [t.to_json() for t in r.traces],
    }


def robot_json(r: RobotResult) -> dict[str, Any]:
    names = places(r.robot)
    return {
        "robot": r.robot.name,
        "verdict": r.verdict.value,
        "track_m": r.robot.track_m,
        "told_by": r.source,
        "ended": r.ended,
        "wheels": [
            {
                "unit": w.unit,
                "axis": AXES[w.axis],
                "place": names[w.unit, w.axis],
                "side": w.side.value,
                "sign": w.sign,
                "diameter_m": w.diameter_m,
                "gear_ratio": w.gear_ratio,
                "turned": _turned(r, w.unit, w.axis),
            }
            for w in r.robot.wheels
        ],
        "checks": [c.to_json() for c in r.checks],
    }


def _turned(r: RobotResult, unit: str, axis: int) -> str | None:
    seen = r.seen.get((unit, axis))
    if seen is None:
        return None
    if seen.place is None or not seen.direction:
        return "none"
    way = "forward" if seen.direction > 0 else "backward"
    names = {**r.elsewhere, **places(r.robot)}
    unit, axis = seen.place
    return f"{names.get(seen.place, f'{unit}.{AXES[axis]}')}, {way}"


def to_json(s: Session) -> dict[str, Any]:
    stops = s.stops or {}
    return {
        "tool": s.tool,
        "time": s.time,
        "config": s.config_file,
        "settings": s.settings.to_json(),
        "ended": s.ended,
        "record": s.record,
        "verdict": overall(s).value,
        "units": {n: unit_json(n, r, stops.get(n)) for n, r in s.results.items()},
        "robots": {n: robot_json(r) for n, r in (s.robots or {}).items()},
        "yaml": s.yaml,
    }


def overall(s: Session) -> Verdict:
    verdicts = {r.verdict for r in s.results.values()}
    verdicts |= {r.verdict for r in (s.robots or {}).values()}
    for v in (Verdict.FAIL, Verdict.WARN):
        if v in verdicts:
            return v
    return Verdict.PASS if verdicts else Verdict.FAIL


def json_text(s: Session) -> str:
    return json.dumps(to_json(s), indent=1, ensure_ascii=False) + "\n"


STYLE = """
body{font-family:sans-serif;margin:1.5em;color:#222;max-width:70em}
table{border-collapse:collapse;margin:.5em 0 1em}
td,th{border:1px solid #ccc;padding:.2em .5em;text-align:left;vertical-align:top;font-size:.9em}
th{background:#f3f3f3}
.pass{background:#e3f5e1}.warn{background:#fff4d6}.fail{background:#fbe0e0}
.not-run{background:#eee;color:#666}
pre{background:#f7f7f7;padding:.6em;overflow:auto;font-size:.85em}
h2{border-bottom:2px solid #ddd;padding-bottom:.2em}
"""


def _row(cells: list[str], cls: str = "", head: bool = False) -> str:
    tag = "th" if head else "td"
    attr = f' class="{cls}"' if cls else ""
    return f"<tr{attr}>" + "".join(f"<{tag}>{escape(c)}</{tag}>" for c in cells) + "</tr>"


def html_text(s: Session) -> str:
    doc = to_json(s)
    out = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>ABH3 commissioning: {escape(s.config_file)}</title>",
        f"<style>{STYLE}</style></head><body>",
        f"<h1>ABH3 commissioning report — {escape(overall(s).value.upper())}</h1>",
        "<table>",
        _row(["configuration", s.config_file]),
        _row(["time", s.time]),
        _row(["tool", s.tool]),
        _row(["settings", ", ".join(f"{k} {v:g}" for k, v in s.settings.to_json().items())]),
    ]
    if s.ended:
        out.append(_row(["ended early", s.ended], "fail"))
    if s.record:
        out.append(_row(["recording", s.record]))
    out.append("</table>")
    out.append("<h2>Summary</h2><table>")
    out.append(_row(["unit", "drive", "verdict", "firmware", "stop at the end"], head=True))
    for name, u in doc["units"].items():
        out.append(
            _row(
                [
                    name,
                    f"{u['abh3_id']} on {u['bus']}, {u['protocol']}, {u['velocity_model']}",
                    u["verdict"],
                    u["firmware"] or "–",
                    u["stop"] or "–",
                ],
                u["verdict"],
            )
        )
    for name, r in doc["robots"].items():
        on = ", ".join(dict.fromkeys(w["unit"] for w in r["wheels"]))
        out.append(
            _row([f"robot {name}", f"{len(r['wheels'])} wheels on {on}", r["verdict"], "–", "–"])
        )
    out.append("</table>")
    for name, u in doc["units"].items():
        out += _unit_html(name, u, s.results[name])
    for name, r in doc["robots"].items():
        out += _robot_html(name, r)
    out.append("<h2>Configuration</h2>")
    out.append(f"<pre>{escape(s.yaml)}</pre>")
    out.append("</body></html>")
    return "\n".join(out) + "\n"


def _unit_html(name: str, u: dict[str, Any], r: UnitResult) -> list[str]:
    out = [f'<h2 id="unit-{escape(name)}">Unit {escape(name)} — {escape(u["verdict"])}</h2>']
    if u["ended"]:
        out.append(f"<p>The sequence ended early: {escape(u['ended'])}</p>")
    out.append("<table>")
    out.append(_row(["step", "check", "verdict", "measured", "limit", "what to change"], head=True))
    for c in u["checks"]:
        cls = c["verdict"].replace(" ", "-")
        fix = c["fix"] if c["verdict"] != "pass" else ""
        out.append(_row([c["step"], c["name"], c["verdict"], c["measured"], c["limit"], fix], cls))
    out.append("</table>")
    if u["can_settings"]:
        out.append("<h3>CAN settings (drive against YAML)</h3><table>")
        out.append(_row(["address", "name", "drive", "YAML", "verdict"], head=True))
        for row in u["can_settings"]:
            out.append(
                _row(
                    [
                        f"0x{row['address']:04X}",
                        row["name"],
                        row["drive"] or "–",
                        row["yaml"],
                        row["verdict"],
                    ]
                )
            )
        out.append("</table>")
    if u["parameters"]:
        out.append("<h3>Drive parameters read</h3><table>")
        out.append(_row(["address", "name", "value"], head=True))
        for p in u["parameters"]:
            out.append(_row([p["address"], p["name"], p["value"]]))
        out.append("</table>")
    for trace in r.traces:
        note = f" — stopped: {trace.stopped}" if trace.stopped else ""
        out.append(f"<h3>{escape(trace.title)}{escape(note)}</h3>")
        out.append(f'<figure data-trace="{escape(trace.title)}">{plot(trace)}</figure>')
    return out


def _robot_html(name: str, r: dict[str, Any]) -> list[str]:
    out = [f'<h2 id="robot-{escape(name)}">Robot {escape(name)} — {escape(r["verdict"])}</h2>']
    out.append(
        f"<p>Track {r['track_m']:g} m. Each wheel alone, forward at creep speed; which "
        f"wheel turned and which way: told by {escape(r['told_by'] or '–')}.</p>"
    )
    if r["ended"]:
        out.append(f"<p>Not all of it ran: {escape(r['ended'])}</p>")
    out.append("<table>")
    out.append(
        _row(
            ["wheel", "place", "sign", "diameter", "gear ratio", "asked forward: turned"],
            head=True,
        )
    )
    for w in r["wheels"]:
        turned = w["turned"] or "–"
        ok = turned == f"{w['place']}, forward"
        out.append(
            _row(
                [
                    f"{w['unit']}.{w['axis']}",
                    w["place"],
                    f"{w['sign']:+d}",
                    f"{w['diameter_m']:g} m",
                    f"{w['gear_ratio']:g}",
                    turned,
                ],
                "" if w["turned"] is None else ("pass" if ok else "fail"),
            )
        )
    out.append("</table><table>")
    out.append(_row(["check", "verdict", "measured", "limit", "what to change"], head=True))
    for c in r["checks"]:
        cls = c["verdict"].replace(" ", "-")
        fix = c["fix"] if c["verdict"] != "pass" else ""
        out.append(_row([c["name"], c["verdict"], c["measured"], c["limit"], fix], cls))
    out.append("</table>")
    return out
