"""Configuration written back as TOML: the run folder's ``config.toml`` and ``configs/default.toml``."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from forcegrasp.config import SECTIONS, Config



def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # JSON string escapes are valid TOML basic strings
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def emit_toml(config: Config, *, comments: bool) -> str:
    """`config` as TOML; with `comments`, each section and key carries its help text."""
    lines: list[str] = []
    for section in SECTIONS:
        table = getattr(config, section)
        if comments:
            lines.append(f"# {type(table).__doc__.strip().splitlines()[0]}")
        lines.append(f"[{section}]")
        nested = []
        for f in dataclasses.fields(table):
            value = getattr(table, f.name)
            if isinstance(value, dict):
                nested.append((f, value))
                continue
            if comments:
                lines.append(f"# {f.metadata['help']}")
            lines.append(f"{f.name} = {_toml_value(value)}")
        for f, value in nested:
            lines.append("")
            if comments:
                lines.append(f"# {f.metadata['help']}")
            lines.append(f"[{section}.{f.name}]")
            if comments and not value and section == "learner":
                lines.extend(_SAC_EXAMPLE)
            lines.extend(f"{k} = {_toml_value(v)}" for k, v in value.items())
        lines.append("")
    return "\n".join(lines)


_SAC_EXAMPLE = [
    "# updates_per_step = 1.0   # update-to-data ratio",
    "# batch_size = 256",
    "# learning_starts = 1000",
    "# gamma = 0.99",
]


def default_config_toml() -> str:
    """The defaults as a commented TOML file (what ``configs/default.toml`` contains)."""
    header = ("# ForceGrasp configuration: shared by the learner, the actors and the evaluator.\n"
              "# Override any key with FORCEGRASP_<SECTION>_<KEY>=value or --set section.key=value.\n\n")
    return header + emit_toml(Config(), comments=True)
