"""The end of a training run, side by side: the actors' online figure, the learner's last
snapshots and the evaluator's pick, each tested on the same held-out placements (issue 15).

A user watching `forcegrasp up` sees the online success (last 100 episodes, sampled actions,
weights changing under them); what they take home is a policy file. This tests the last
``--last`` snapshots of a run (at least ``--spacing`` environment steps apart), its evaluator's
pick and, for the final snapshot, sampled actions too, on ``--episodes`` held-out placements, and
sets the online figure at each snapshot's step beside them. It also gives the spread of the
evaluator's own 10-placement scores over the run's last ``--window`` steps against the binomial
noise of that many episodes: a spread near the noise means snapshots do not swing.

    python bench/snapshot_spread.py runs/n-fast-camera-long-s0 --json spread.json
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

from forcegrasp.cli.experiment import online_at, test_files
from forcegrasp.cli.plot import read_scalars
from forcegrasp.rundir import RunDir


def last_snapshots(run: RunDir, last: int, spacing: int) -> list[tuple[int, Path]]:
    """(step, file) of the newest snapshots, newest first, at least ``spacing`` steps apart."""
    found = sorted(((int(p.stem.split("-")[1]), p) for p in run.checkpoints.glob("policy-*.safetensors")), reverse=True)
    out: list[tuple[int, Path]] = []
    for step, path in found:
        if not out or out[-1][0] - step >= spacing:
            out.append((step, path))
        if len(out) == last:
            break
    return out


def sampled_success(path: Path, episodes: int, seed: int) -> float:
    """The same held-out placements with sampled actions (as the actors act)."""
    from forcegrasp.env import FunctionalGraspEnv
    from forcegrasp.evaluation import placements
    from forcegrasp.policy import Policy

    policy = Policy.load(path, seed=seed)
    env = FunctionalGraspEnv.for_policy(policy.metadata)
    wins = 0
    for place in placements(seed, episodes, env.jitter, "test", clear=env.is_clear):
        obs, _ = env.reset(seed=place.seed, options={"offset": place.offset})
        while True:
            obs, _, terminated, truncated, info = env.step(policy(obs, deterministic=False))
            if terminated or truncated:
                break
        wins += bool(info["success"])
    return wins / episodes


def evaluator_spread(run: RunDir, window: int) -> dict | None:
    """Mean and sd of the evaluator's per-checkpoint success over the last ``window`` steps."""
    index = run.read_index()
    if not index or not index.get("history"):
        return None
    hist = sorted(index["history"], key=lambda h: h["step"])
    last = [h for h in hist if h["step"] >= hist[-1]["step"] - window]
    rates = np.array([h["success_rate"] for h in last])
    n = int(last[-1].get("episodes", 10))
    p = float(rates.mean())
    return {"checkpoints": len(last), "episodes_each": n, "mean": round(p, 3), "sd": round(float(rates.std()), 3),
            "binomial_sd": round(float(np.sqrt(p * (1 - p) / n)), 3)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--last", type=int, default=5)
    parser.add_argument("--spacing", type=int, default=10_000, help="environment steps between tested snapshots")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0, help="held-out placement stream (the 'test' stream)")
    parser.add_argument("--window", type=int, default=60_000, help="steps of evaluator history for the spread")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    run = RunDir(args.run)
    snaps = last_snapshots(run, args.last, args.spacing)
    best = run.best_policy()
    files = [p for _, p in snaps] + ([best] if best is not None else [])
    scores = test_files(files, args.episodes, args.seed, {}, os.cpu_count() or 1)
    scalars = read_scalars(run.tensorboard) if run.tensorboard.is_dir() else {}
    rows = []
    for (step, path), score in zip(snaps, scores):
        online = online_at(scalars, step)
        rows.append({"file": path.name, "step": step, "held_out": score["success_rate"],
                     "online": None if online is None else online["success_rate"]})
    rows[0]["held_out_sampled"] = sampled_success(snaps[0][1], args.episodes, args.seed)
    result = {"run": str(args.run), "episodes": args.episodes, "snapshots": rows,
              "evaluator_pick": None if best is None else {"file": best.name, "held_out": scores[-1]["success_rate"]},
              "evaluator_spread": evaluator_spread(run, args.window)}
    print("| snapshot (env steps) | online success(100) at that step | held-out success |")
    print("|---:|---:|---:|")
    for r in rows:
        extra = f" (sampled actions: {r['held_out_sampled']:.0%})" if "held_out_sampled" in r else ""
        online = "-" if r["online"] is None else f"{r['online']:.0%}"
        print(f"| {r['step']:,} | {online} | {r['held_out']:.0%}{extra} |")
    if best is not None:
        print(f"| evaluator's pick ({best.name}) | | {scores[-1]['success_rate']:.0%} |")
    print("evaluator spread:", result["evaluator_spread"])
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
