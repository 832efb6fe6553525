"""Solvability of each FunctionalGrasp task by the scripted straight approach.

Told the true object offset it shows the labels make the task solvable; blind to the
jitter (aiming at the nominal pose) it shows what an open-loop approach achieves, the gap
force feedback has to close. Same 50 placements for both.

    python bench/scripted_solvability.py [--placements 50]
"""

from __future__ import annotations

import argparse
from collections import Counter

from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.objects import list_objects
from forcegrasp.scripted import jitter_offsets, success_rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--placements", type=int, default=50)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("objects", nargs="*")
    args = parser.parse_args()
    print("| object | told the offset | blind to the jitter | blind failures |")
    print("|---|---|---|---|")
    for name in args.objects or list_objects():
        env = FunctionalGraspEnv(name)
        offsets = jitter_offsets(args.placements, seed=args.seed, env=env)
        told, _ = success_rate(env, offsets, told=True)
        blind, results = success_rate(env, offsets, told=False)
        failures = Counter(r["failure"] for r in results if not r["success"])
        print(f"| {name} | {told:.0%} | {blind:.0%} | {dict(failures)} |", flush=True)


if __name__ == "__main__":
    main()
