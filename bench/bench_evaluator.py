"""Evaluation throughput with MCAP episode logging on vs off (goal: logging costs <= 10 %).

    python bench/bench_evaluator.py --object mug --episodes 8 --reps 3

Runs what the evaluator runs — a deterministic policy (the SAC actor at its real size, 256x256,
randomly initialised) on fixed jittered placements, one process, one torch thread — and times
every episode three ways, interleaved episode by episode (the order of the modes rotates):
logging off, logging with the foxglove-sdk writer, logging with the pure-Python ``mcap``
writer. Every mode plays the very same episodes (same placement, same policy, deterministic
physics), so each logged episode has an unlogged twin run moments before or after it.

Reported per mode: episodes/s and steps/s over all its episodes (wall clock), and the overhead
against "off" as the median over episodes of (time logged / time of its unlogged twin) - 1, in
wall-clock time and in CPU time of this process (``time.process_time``). The paired median is
what stays stable on a shared machine, where other processes slow whole seconds at random.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="mug")
    parser.add_argument("--episodes", type=int, default=8, help="placements (episodes per mode and repetition)")
    parser.add_argument("--reps", type=int, default=3, help="repetitions over all placements")
    parser.add_argument("--max-steps", type=int, default=200)
    parser.add_argument("--hidden", type=int, nargs="+", default=[256, 256])
    parser.add_argument("--json", default=None, help="also write the results here")
    args = parser.parse_args(argv)

    import torch

    from forcegrasp.config import load_config
    from forcegrasp.mcap_log import EpisodeLogger
    from forcegrasp.policy import Actor, Policy, configure_threads
    from forcegrasp.runtime import make_env, policy_metadata
    from forcegrasp.evaluation import placements, run_episode

    configure_threads(1)
    torch.manual_seed(0)
    config = load_config(env={}, overrides=[f"env.object={args.object}", f"env.max_steps={args.max_steps}"])
    env = make_env(config)
    meta = policy_metadata(config, args.hidden)
    policy = Policy.from_actor(Actor(meta.obs_dim, meta.act_dim, tuple(args.hidden)), meta, seed=0)
    places = placements(config.run.seed, args.episodes, config.env.jitter, "eval", env.is_clear)
    modes = ["off", "sdk", "mcap"] if importlib.util.find_spec("foxglove") else ["off", "mcap"]

    with tempfile.TemporaryDirectory() as tmp:
        def episode(mode: str, place, tag: str) -> dict:
            logger = None if mode == "off" else EpisodeLogger(Path(tmp) / f"{tag}.mcap", env, backend=mode)
            t0, c0 = time.perf_counter(), time.process_time()
            r = run_episode(env, policy, place, logger)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            size = (Path(tmp) / f"{tag}.mcap").stat().st_size if logger else 0
            return {"wall": wall, "cpu": cpu, "steps": r.length, "ret": r.ret, "bytes": size}

        for mode in modes:  # warm-up: first-call costs of torch, MuJoCo, the writers
            episode(mode, places[0], f"warm-{mode}")
        runs: dict[str, list[dict]] = {m: [] for m in modes}
        for rep in range(args.reps):
            for i, place in enumerate(places):
                order = modes[(i + rep) % len(modes):] + modes[:(i + rep) % len(modes)]
                for mode in order:
                    runs[mode].append(episode(mode, place, f"{mode}-{rep}-{i}"))
            done = {m: sum(x["steps"] for x in runs[m]) / sum(x["wall"] for x in runs[m]) for m in modes}
            print(f"rep {rep}: " + "  ".join(f"{m} {v:.0f} steps/s" for m, v in done.items()), flush=True)

    same = all(a["ret"] == b["ret"] for m in modes for a, b in zip(runs[m], runs["off"]))
    steps = sum(x["steps"] for x in runs["off"])
    print(f"\n{args.object}, {args.episodes} placements x {args.reps} reps = {len(runs['off'])} episodes per mode "
          f"({steps} env steps), policy {args.hidden}, identical episodes in every mode: {same}")
    print(f"{'mode':>6} {'episodes/s':>11} {'steps/s':>9} {'overhead (wall)':>16} {'overhead (CPU)':>15} "
          f"{'MCAP B/step':>12} {'KB/episode':>11}")
    summary = {}
    for m in modes:
        wall = sum(x["wall"] for x in runs[m])
        ratio_wall = statistics.median(x["wall"] / o["wall"] for x, o in zip(runs[m], runs["off"])) - 1
        ratio_cpu = statistics.median(x["cpu"] / o["cpu"] for x, o in zip(runs[m], runs["off"])) - 1
        size = sum(x["bytes"] for x in runs[m])
        summary[m] = {"episodes_per_s": len(runs[m]) / wall, "steps_per_s": steps / wall, "overhead_wall": ratio_wall,
                      "overhead_cpu": ratio_cpu, "bytes_per_step": size / steps, "bytes_per_episode": size / len(runs[m])}
        s = summary[m]
        print(f"{m:>6} {s['episodes_per_s']:11.3f} {s['steps_per_s']:9.1f} {ratio_wall:16.1%} {ratio_cpu:15.1%} "
              f"{s['bytes_per_step']:12.0f} {s['bytes_per_episode'] / 1024:11.1f}")
    print(f"load average at the end: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "summary": summary, "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
