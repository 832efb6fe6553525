"""The recipe's ablation table from `forcegrasp experiment` records: each lever setting, per object
and force-feedback arm, with held-out success of the evaluator's pick at 10 / 20 / 40 / 60
minutes, mean and range over seeds, and how many seeds reached each mark; then the axis that does
not depend on the machine: the environment steps the first pick at or above 90 % was trained on,
and each run's environment steps per second (the same two cores ran 110-430 steps/s at different
times, so minutes compare only between runs of one time).

Levers are read from each record: its `effective` SAC settings and demonstrations (what the run
trained with), and the actor and env keys of `RUN_LEVERS` in its configuration (environments per
actor, action step sizes, torque history, proprioception, randomisation), and named by how they
differ from the baseline on that object, "fast (fixed conditions)": the default recipe
(`forcegrasp.recipes.recipe_settings`, `demo_episodes`) at the paper's fixed conditions, without
the observation normalisation that joined it with the randomisation; so a record says itself what it
measured; runs at the action step sizes of `FIRST_ACTION_STEPS` read "first action steps". A mark a
run never reached is "–", never a guess; the table's last columns say how long each group's runs
were and how fast they ran. Only version-2 records are read (`forcegrasp.cli.experiment.check_record`);
records scored on a mix of test conditions are `bench/robustness_table.py`'s.

    python bench/ablation_table.py experiments/*.json
    python bench/ablation_table.py --write docs/recipe.md experiments/*.json   # between its markers
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
from collections import defaultdict
from pathlib import Path

from forcegrasp.cli.experiment import RecordError, read_record
from forcegrasp.config import Config
from forcegrasp.markdown import replace_between
from forcegrasp.recipes import demo_episodes, recipe_settings
from forcegrasp.sac import SACConfig
from forcegrasp.task import ACTION_STEP_KEYS

MARKS = (10.0, 20.0, 40.0, 60.0)
#: Action step sizes named as one term, "first action steps" (2/3 of today's default), in place of
#: three "key = value" terms.
FIRST_ACTION_STEPS = (0.004, 0.02, 0.025)
#: Levers outside [learner.sac], by section; named by their key alone.
RUN_LEVERS = {"actor": ("demo_episodes", "num_actors", "envs_per_actor"),
              "env": ("max_translation_step", "max_rotation_step", "max_h_step", "torque_history", "proprioception",
                      "mass_scale", "mass_scale_range", "torque_noise_range", "jitter_range", "torque_filter", "curriculum_success")}
OFF = {f.name: f.default for f in dataclasses.fields(SACConfig) if f.default is not dataclasses.MISSING}
OFF.update({key: getattr(getattr(Config(), section), key) for section, keys in RUN_LEVERS.items() for key in keys})
OFF["demo_episodes"] = 0  # its default (-1) is per object: `default_for`
# The table's runs are at the paper's fixed conditions (randomised runs are scored on a mix of test
# conditions: the robustness table's), which is also what a record made before these keys existed
# trained with.
OFF.update(mass_scale_range=[], torque_noise_range=[], jitter_range=[])
#: The table's baseline, "fast (fixed conditions)": the default recipe without what joined it with
#: the randomisation (observation normalisation tied at fixed conditions: a row of its own).
ROBUST_ONLY = {"obs_norm": False}


def default_for(object_name: str) -> dict:
    """The baseline's settings on one object (demonstrations and `OBJECT_RECIPES` are per object)."""
    return {**OFF, **recipe_settings("fast", object_name), **ROBUST_ONLY,
            "demo_episodes": demo_episodes(object_name, -1)}


def _same(a, b) -> bool:
    """Equal once JSON's lists are read as the tuples SACConfig holds."""
    return (tuple(a) if isinstance(a, list) else a) == (tuple(b) if isinstance(b, list) else b)


def settings(record: dict) -> dict:
    """The SAC levers and the `RUN_LEVERS` a record trained with (those away from their defaults; a
    key its configuration lacks is at the default)."""
    config, effective = record["config"], record["effective"]
    sac = {k: v for k, v in effective["sac"].items() if k in OFF and k != "seed" and not _same(v, OFF[k])}
    run = {key: (config.get(section) or {}).get(key, OFF[key]) for section, keys in RUN_LEVERS.items() for key in keys}
    run["demo_episodes"] = effective["demo_episodes"]
    return {**sac, **{k: v for k, v in run.items() if v != OFF[k]}}


def lever_name(levers: dict, object_name: str = "") -> str:
    """How a setting differs from the baseline on that object, e.g. 'fast (fixed conditions)',
    'fast, − privileged_critic'.

    Keys are compared at their effective values (SACConfig's defaults under the recipe), so a lever
    left out and one set to its SACConfig default are the same setting: "− key"."""
    levers, default = {**OFF, **levers}, default_for(object_name)
    first_steps = tuple(levers[k] for k in ACTION_STEP_KEYS) == FIRST_ACTION_STEPS
    diff = [f"− {k}" if v == OFF.get(k, 0) else f"{k} = {v}" + (" (not Table I)" if k == "torque_history" else "")
            for k, v in sorted(levers.items()) if default.get(k, 0) != v and not (first_steps and k in ACTION_STEP_KEYS)]
    if first_steps and FIRST_ACTION_STEPS != tuple(default[k] for k in ACTION_STEP_KEYS):
        diff = sorted(diff + ["first action steps"])
    return "fast" + "".join(f", {d}" for d in diff) if diff else "fast (fixed conditions)"


def success_at(record: dict, minute: float) -> float | None:
    for mark in record.get("marks", []):
        if abs(mark["minute"] - minute) < 1e-6:
            best = mark.get("test", {}).get("best")  # none: a run without the evaluator
            return None if best is None else best["success_rate"]
    return None


def steps_to(record: dict, rate: float = 0.9) -> int | None:
    """Env steps the evaluator's pick had trained on at the first mark where it scored >= rate."""
    for mark in sorted(record.get("marks", []), key=lambda m: m["minute"]):
        best = mark.get("test", {}).get("best")
        if best is not None and best["success_rate"] >= rate and "best" in mark.get("steps", {}):
            return int(mark["steps"]["best"])
    return None


def steps_per_s(record: dict) -> float | None:
    """The run's environment steps per wall-clock second (the machine's speed as the run saw it)."""
    last = max(record.get("marks", []), key=lambda m: m["minute"], default=None)
    if last is None or "latest" not in last.get("steps", {}) or not last.get("elapsed_s"):
        return None
    return last["steps"]["latest"] / last["elapsed_s"]


def steps_cell(records: list[dict]) -> str:
    reached = [s for r in records if (s := steps_to(r)) is not None]
    if not reached:
        return f"– (0 of {len(records)})"
    k = [s / 1000 for s in reached]
    spread = f" [{min(k):.0f}–{max(k):.0f}]" if len(k) > 1 else ""
    return f"{statistics.median(k):.0f} k{spread} ({len(k)} of {len(records)})"


def cell(values: list[float]) -> str:
    if not values:
        return "–"
    mean = 100 * statistics.fmean(values)
    if len(values) == 1:
        return f"{mean:.0f} % (n=1)"
    return f"{mean:.0f} % [{100 * min(values):.0f}–{100 * max(values):.0f}] (n={len(values)})"


def table(paths: list[Path]) -> str:
    """The markdown table of the records at ``paths``; a `RecordError` for a file that is not a
    version-2 experiment record."""
    groups = defaultdict(list)
    for path in paths:
        record = read_record(path)
        if record.get("conditions") or len(record.get("objects") or []) > 1:
            continue  # a mix of test conditions: the robustness table's; several objects: mark_table's
        key = (record["object"], bool(record["force_feedback"]), lever_name(settings(record), record["object"]))
        groups[key].append(record)
    lines = ["| object | force feedback | setting | seeds | " + " | ".join(f"{m:.0f} min" for m in MARKS)
             + " | to 90 %: pick's env steps, median [range] | run lengths | env steps/s |",
             "|---|---|---|---|" + "---:|" * len(MARKS) + "---|---|---|"]
    for (obj, ff, name), records in sorted(groups.items()):
        records = sorted(records, key=lambda r: r["seed"])  # seeds, lengths and speeds in one order
        seeds = ", ".join(str(r["seed"]) for r in records)
        cells = [cell([v for r in records if (v := success_at(r, m)) is not None]) for m in MARKS]
        lengths = ", ".join(f"{r['marks'][-1]['minute']:.0f}" for r in records) + " min"
        speeds = ", ".join("?" if (v := steps_per_s(r)) is None else f"{v:.0f}" for r in records)
        lines.append(f"| {obj} | {'yes' if ff else 'no'} | {name} | {seeds} | " + " | ".join(cells)
                     + f" | {steps_cell(records)} | {lengths} | {speeds} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("records", nargs="+", type=Path)
    parser.add_argument("--write", type=Path, help="put the table between this page's <!-- ablation-table --> markers")
    args = parser.parse_args(argv)
    try:
        text = table(args.records)
    except (RecordError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.write is None:
        print(text)
    elif not replace_between(args.write, "ablation-table", text.splitlines()):
        print(f"error: {args.write}: no <!-- ablation-table --> ... <!-- /ablation-table --> markers", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
