"""The robustness table from `forcegrasp experiment` records tested under several conditions: per
run, the held-out success of the evaluator's pick at each mark under every test condition
(`forcegrasp.conditions`), their mean, and the run's environment steps and steps per second; a
run is named as its record (``experiments/<name>.json``).
Only records of one object made with ``evaluator.conditions`` take part; every file must be a version-2 experiment
record (`forcegrasp.cli.experiment.check_record`).

    python bench/robustness_table.py experiments/*.json
    python bench/robustness_table.py --write docs/recipe.md experiments/*.json   # between its markers
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from forcegrasp.cli.experiment import RecordError, read_record
from forcegrasp.markdown import replace_between

MARKER = "robustness-table"


def randomisation(record: dict) -> str:
    """The run's training-time randomisation, and the levers beside it (observation normalisation,
    a torque filter, demonstrations), in words."""
    env = record.get("config", {}).get("env", {})
    parts = []
    if env.get("mass_scale_range"):
        low, high = env["mass_scale_range"]
        parts.append(f"mass {low:g}–{high:g}×")
    if env.get("torque_noise_range"):
        low, high = env["torque_noise_range"]
        parts.append(f"noise {low:g}–{high:g} N·m")
    if env.get("jitter_range"):
        low, high = env["jitter_range"]
        parts.append(f"jitter ±{low * 100:g}–{high * 100:g} cm")
    if env.get("torque_filter", 1.0) < 1:
        parts.append(f"torque filter {env['torque_filter']:g}")
    if record.get("effective", {}).get("sac", {}).get("obs_norm"):
        parts.append("observation normalisation")
    noise = record.get("effective", {}).get("sac", {}).get("actor_torque_noise")
    if noise:
        parts.append(f"actor's loss noise 0–{noise:g} N·m")
    if env.get("curriculum_success"):
        parts.append(f"opened at {env['curriculum_success']:.0%} success")
    demos = record.get("effective", {}).get("demo_episodes")
    if demos is not None and demos != 4:
        parts.append(f"{demos} demonstrations")
    return ", ".join(parts) or "none (5× only)"


def rows(records: list[dict]) -> list[str]:
    conditions = list(dict.fromkeys(c for r in records for c in r.get("conditions") or []))
    head = ["| run | object | seed | randomisation | mark | " + " | ".join(conditions) + " | mean | env steps | steps/s |",
            "|---|---|---:|---|---:|" + "---:|" * len(conditions) + "---:|---:|---:|"]
    out = []
    for r in sorted(records, key=lambda r: (r["object"], randomisation(r), r["seed"], r["config"]["run"]["name"])):
        for m in r["marks"]:
            pick = m.get("test", {}).get("best")
            if pick is None or "conditions" not in pick:
                continue
            cells = [f"{pick['conditions'][c]['success_rate']:.0%}" if c in pick["conditions"] else "–"
                     for c in conditions]
            steps = m.get("steps", {})
            rate = steps.get("latest", 0) / m["elapsed_s"] if m.get("elapsed_s") else 0
            out.append(f"| `{r['config']['run']['name']}` | {r['object']} | {r['seed']} | {randomisation(r)} | {m['minute']:.0f} min | "
                       + " | ".join(cells) + f" | **{pick['success_rate']:.0%}** | {steps.get('best', 0) / 1000:.0f} k "
                       f"| {rate:.0f} |")
    return head + out if out else []


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("records", nargs="+", type=Path)
    parser.add_argument("--write", type=Path, help="put the table between this page's markers instead of printing it")
    args = parser.parse_args(argv)
    try:
        records = [r for r in map(read_record, args.records)  # one object's runs (several: mark_table.py)
                   if r.get("conditions") and len(r.get("objects") or []) <= 1]
    except (RecordError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    lines = rows(records)
    if args.write:
        if not replace_between(args.write, MARKER, lines):
            raise SystemExit(f"{args.write}: no <!-- {MARKER} --> ... <!-- /{MARKER} --> markers")
        print(f"wrote {len(lines)} lines into {args.write}")
    else:
        print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
