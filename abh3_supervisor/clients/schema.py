"""``abh3 schema``: the JSON Schema of the configuration, core and installed plugins.

Point an editor at it (yaml-language-server: ``# yaml-language-server: $schema=…`` as the
file's first line) for completion, descriptions and checking as you type; ``abh3 check``
remains the full check (names, addresses, timing rules, the bus-load plan).
"""

from __future__ import annotations

import json
import sys
from typing import Any

from abh3_supervisor.config.schema import document, plugin_section
from abh3_supervisor.plugin_host.host import section_schemas


def config_schema() -> dict[str, Any]:
    """The whole schema; plugins that cannot say are left free-form, with a warning."""
    schemas, problems = section_schemas()
    for name, problem in problems.items():
        print(f"warning: plugin {name}: no schema for its section: {problem}", file=sys.stderr)
    sections = {
        name: plugin_section(
            schema, f"plugin {name}" + ("" if schema else " (it describes no settings)")
        )
        for name, schema in schemas.items()
    }
    return document(sections)


def schema_text() -> str:
    return json.dumps(config_schema(), indent=2, ensure_ascii=False) + "\n"
