"""Solvability of each FunctionalGrasp task by the scripted straight approach.

Told the true object offset it shows the labels make the task solvable; blind to the
jitter (aiming at the nominal pose) it shows what an open-loop approach achieves, the gap
force feedback has to close. With ``--conditions`` it is the reference row of the robustness
tests: the same approach under each test condition (`forcegrasp.conditions`), on the held-out
placements `forcegrasp experiment` and `forcegrasp eval` test on (the ``test`` stream).

    python bench/scripted_solvability.py [--placements 50] [objects...]
    python bench/scripted_solvability.py --conditions 5x 1x_3cm 0.5x_3cm noise_0.5 jitter_3cm --placements 100 mug
"""

from __future__ import annotations

import argparse
from collections import Counter

from forcegrasp.conditions import CONDITIONS, env_kwargs
from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.evaluation import placements
from forcegrasp.objects import list_objects
from forcegrasp.scripted import jitter_offsets, run_episode, success_rate


def by_condition(name: str, conditions: list[str], n: int, seed: int) -> dict[str, tuple[float, float]]:
    """(told, blind) success under each condition, on the held-out placements of that condition."""
    out = {}
    for condition in conditions:
        env = FunctionalGraspEnv(name, **env_kwargs(condition))
        places = placements(seed, n, env.jitter, "test", clear=env.is_clear)
        told, blind = ([run_episode(env, p.offset, told=t, seed=p.seed)["success"] for p in places] for t in (True, False))
        out[condition] = (sum(told) / n, sum(blind) / n)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--placements", type=int, default=50)
    parser.add_argument("--seed", type=int, default=None, help="placement seed (default: 1; with --conditions 0, "
                        "the held-out stream of forcegrasp experiment)")
    parser.add_argument("--conditions", nargs="+", choices=list(CONDITIONS), help="test conditions to run under")
    parser.add_argument("objects", nargs="*")
    args = parser.parse_args()
    names = args.objects or list_objects()
    if args.conditions:
        seed = 0 if args.seed is None else args.seed
        print(f"Scripted approach, told the offset / blind, {args.placements} held-out placements (seed {seed})\n")
        print("| object | " + " | ".join(args.conditions) + " |")
        print("|---|" + "---|" * len(args.conditions))
        for name in names:
            rates = by_condition(name, args.conditions, args.placements, seed)
            print(f"| {name} | " + " | ".join(f"{t:.0%} / {b:.0%}" for t, b in rates.values()) + " |", flush=True)
        return
    print("| object | told the offset | blind to the jitter | blind failures |")
    print("|---|---|---|---|")
    for name in names:
        env = FunctionalGraspEnv(name)
        offsets = jitter_offsets(args.placements, seed=1 if args.seed is None else args.seed, env=env)
        told, _ = success_rate(env, offsets, told=True)
        blind, results = success_rate(env, offsets, told=False)
        failures = Counter(r["failure"] for r in results if not r["success"])
        print(f"| {name} | {told:.0%} | {blind:.0%} | {dict(failures)} |", flush=True)


if __name__ == "__main__":
    main()
