"""The report's summaries of measured episodes: success rates with 95 % Wilson intervals per
shipped policy and experiment (`summarise`), per policy of several objects (`summarise_generalists`)
and for the scripted rows (`summarise_scripted`), the tables and figures of ``forcegrasp report``
are drawn from (`forcegrasp.report` runs the episodes)."""

from __future__ import annotations

import json
from collections import Counter

from forcegrasp.report import Shipped, wilson


def _rate(eps: list[dict]) -> dict:
    k, n = sum(e["success"] for e in eps), len(eps)
    return {"successes": k, "episodes": n, "rate": k / n, "ci95": wilson(k, n)}


def summarise(policies: list[Shipped], results: dict) -> dict:
    """Success rates with 95 % intervals per one-object policy and experiment (docs/results.md's table)."""
    out = {}
    for s in policies:
        if s.multi:
            continue
        r = results[s.name]
        row = {"object": s.obj, "force_feedback": s.force_feedback, "proprioception": s.proprioception,
               "randomised": s.randomised, "seed": s.meta.get("seed"), "env_steps": s.meta.get("env_steps"),
               "wall_clock_min": s.meta.get("wall_clock_min")}
        for kind in ("held_out", "mass", "noise", "condition"):
            row[kind] = {value: _rate(eps) for value, eps in r.get(kind, {}).items()}
        out[s.name] = row
    return out


def summarise_generalists(policies: list[Shipped], results: dict) -> dict:
    """Per policy of several objects: its objects, arm, seed, and the success on each object it
    trained on (``object``) and zero-shot on each it never saw (``unseen``, with its failure modes)."""
    out = {}
    for s in (s for s in policies if s.multi):
        r = results[s.name]
        row = {"objects": s.objects, "force_feedback": s.force_feedback, "proprioception": s.proprioception,
               "seed": s.meta.get("seed"), "env_steps": s.meta.get("env_steps"),
               "wall_clock_min": s.meta.get("wall_clock_min"),
               "object": {o: _rate(eps) for o, eps in r.get("object", {}).items()},
               "unseen": {o: {**_rate(eps), "failures": dict(Counter(e["failure"] for e in eps if not e["success"]))}
                          for o, eps in r.get("unseen", {}).items()}}
        out[s.name] = row
    return out


def summarise_scripted(scripted: dict, carried: dict | None = None) -> dict:
    """The scripted rows' success rates, ``{object: {"told" | "blind": {kind: {value: cell}}}}``:
    the cells ``carried`` over from a previous report (`carried_over`), with those just run."""
    out = json.loads(json.dumps(carried or {}))
    for obj, per_obj in scripted.items():
        for mode, kinds in per_obj.items():
            for kind, values in kinds.items():
                cells = out.setdefault(obj, {}).setdefault(mode, {}).setdefault(kind, {})
                cells.update({value: _rate(eps) for value, eps in values.items()})
    return out
