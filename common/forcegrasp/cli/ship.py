"""``forcegrasp ship RUN``: copy a run's picked policy into ``assets/policies/`` with its record.

The pick is the paper's: the evaluator's five best checkpoints, re-scored on 100 placements, the
best of them (`forcegrasp experiment` freezes it at each mark; ``--mark`` picks one, default the
last). The shipped file is tested again on ``--episodes`` held-out placements (the ``"test"``
stream, never used to pick) and the JSON sidecar records what `forcegrasp report` and a reader
need: object, observation arm (force feedback and proprioception, read from the policy file),
seed, environment steps and wall-clock to the pick, the recipe, the training conditions, the score.
Name: ``<object>-<ff|noff>[-cmd][-5x]-s<seed>.safetensors`` (``-cmd``: commanded proprioception;
``-5x``: trained at the paper's fixed conditions only, without the default recipe's randomised
mass, torque noise and placement width, `forcegrasp.report.randomised`). A policy of
several objects is named for its set (``camera+mug-ff-s0``), tested on each object, and its sidecar
records ``objects`` and the score on each (``held_out`` is the worst object's).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path


def picked_by(ev: dict) -> str:
    """How the run's evaluator picked its best checkpoint, in words (from its configuration)."""
    per = f" per condition ({', '.join(ev['conditions'])}), ranked on their mean" if ev.get("conditions") else ""
    return (f"the evaluator's top {ev['top_k']} by {ev['eval_episodes']} placements{per}, re-scored on "
            f"{ev['final_rank_episodes']} each; the best")


def ship(run_dir: Path, out_dir: Path, mark: float | None, episodes: int, workers: int, log=print) -> Path:
    from forcegrasp.cli.experiment import load_record, test_files
    from forcegrasp.conditions import env_kwargs
    from forcegrasp.multi_object import policy_objects
    from forcegrasp.policy_file import load_policy_file
    from forcegrasp.report import randomised
    from forcegrasp.task import proprioception_of

    record = load_record(run_dir)
    if record is None:
        raise ValueError(f"{run_dir}: no experiment.json (ship takes runs made with forcegrasp experiment)")
    marks = [m for m in record["marks"] if "best" in m["files"]]
    if mark is not None:
        marks = [m for m in marks if abs(m["minute"] - mark) < 1e-6]
    if not marks:
        raise ValueError(f"{run_dir}: no mark{'' if mark is None else f' at minute {mark:g}'} with an evaluator's pick")
    m = marks[-1]
    src = run_dir / "marks" / m["files"]["best"]
    meta = load_policy_file(src)[1]
    proprioception = proprioception_of(meta)
    arm = ("ff" if meta.force_feedback else "noff") + ("-cmd" if proprioception == "commanded" else "")
    arm += "" if randomised(record["config"]["env"]) else "-5x"
    objects = policy_objects(meta)
    dst = out_dir / f"{'+'.join(objects)}-{arm}-s{record['seed']}.safetensors"
    log(f"testing {src} on {episodes} held-out placements" + (" of each object" if len(objects) > 1 else ""))
    # at the paper's training conditions, whatever ranges the policy trained on (forcegrasp.conditions)
    each = {o: test_files([src], episodes, record.get("test_seed", 0), {**env_kwargs("5x"), "object_name": o},
                          workers, log)[0] for o in objects}
    score = min(each.values(), key=lambda r: r["success_rate"])
    out_dir.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst.with_suffix(".tmp"))
    os.replace(dst.with_suffix(".tmp"), dst)
    sac = record["config"]["learner"]
    effective = record["effective"]  # what the run trained with
    sidecar = {
        "object": meta.object_name, **({"objects": objects} if len(objects) > 1 else {}),
        "force_feedback": bool(meta.force_feedback), "proprioception": proprioception,
        "seed": record["seed"],
        "picked_step": int(meta.training_steps),
        "env_steps": int(m["steps"].get("latest", meta.training_steps)),
        "wall_clock_min": float(m["minute"]),
        "picked_by": picked_by(record["config"]["evaluator"]),
        "held_out": {"episodes": score["episodes"], "success_rate": score["success_rate"],
                     "mean_return": round(score["mean_return"], 2), "stream": "test", "seed": record.get("test_seed", 0),
                     "condition": "5x",
                     **({"objects": {o: {"episodes": r["episodes"], "success_rate": r["success_rate"]}
                                     for o, r in each.items()}} if len(objects) > 1 else {})},
        "recipe": {"name": sac.get("recipe"), "overrides": sac.get("sac", {}),
                   "actor": {**{k: record["config"]["actor"][k] for k in ("num_actors", "envs_per_actor")
                                if k in record["config"]["actor"]},
                             "demo_episodes": effective["demo_episodes"]},
                   # every SAC setting the run trained with, its recipe's per-object ones included
                   "sac": effective["sac"]},
        "env": record["config"]["env"],
        "run": {"name": record["config"]["run"]["name"], "label": record.get("label"),
                "machine": "2 CPU cores, no GPU; learner, 2 actors x 8 envs and the evaluator"},
    }
    dst.with_suffix(".json").write_text(json.dumps(sidecar, indent=1) + "\n")
    log(f"wrote {dst} ({score['success_rate']:.0%} on {score['episodes']} held-out placements) and {dst.with_suffix('.json').name}")
    return dst


def main(argv=None) -> int:
    from forcegrasp.report import POLICIES_DIR

    parser = argparse.ArgumentParser(prog="forcegrasp ship", description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="run folder of a forcegrasp experiment")
    parser.add_argument("--mark", type=float, default=None, help="minute of the mark to ship (default: the last)")
    parser.add_argument("--out", type=Path, default=POLICIES_DIR, help=f"folder (default {POLICIES_DIR})")
    parser.add_argument("--episodes", type=int, default=100, help="held-out placements of the final test")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args(argv)
    try:
        ship(args.run, args.out, args.mark, args.episodes, args.workers, log=lambda s: print(s, flush=True))
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
