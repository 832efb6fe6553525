"""One actor process's env steps/s against the raw physics rate of its envs, side by side.

The actor side is the service's own stepping code (``ActorService.step_all``: the actor role plus encoding): a batched
forward pass of a real-size policy (77-256-256-14) for all its envs, the env steps, resets and
the encoding of TransitionBatch messages. The raw side replays the control sequences those
envs produced with nothing but ``d.ctrl[:] = u; mj_step(m, d, nstep=frame_skip)`` per env, so
both simulate the same contacts. Each repetition runs actor, raw, raw, actor (A-B-B-A).

    python bench/bench_actor.py --envs 8 --steps 400 --reps 3
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np

from forcegrasp.config import load_config
from forcegrasp.policy import Actor, Policy, configure_threads
from forcegrasp.runtime import policy_metadata
from forcegrasp_actor.actor import ActorService


def record(service: ActorService, iterations: int):
    """Run the actor's loop body; returns seconds and each env's (ctrl sequence, reset states)."""
    n = len(service.envs)
    ctrls = [[] for _ in range(n)]
    resets = [{0: env.data.qpos.copy()} for env in service.envs]
    counts = [0] * n
    t0 = time.perf_counter()
    for _ in range(iterations):
        episodes_before = [env.steps for env in service.envs]
        service.step_all()
        for i, env in enumerate(service.envs):
            ctrls[i].append(env.data.ctrl.copy() if env.steps else None)
            counts[i] += 1
            if env.steps < episodes_before[i] + 1:  # the env reset after this step
                resets[i][counts[i]] = env.data.qpos.copy()
    return time.perf_counter() - t0, ctrls, resets


def raw(models, ctrls, resets, frame_skip: int) -> float:
    """Bare physics, interleaved across envs exactly as the actor steps them."""
    datas = [mujoco.MjData(m) for m in models]
    n_steps = len(ctrls[0])
    t0 = time.perf_counter()
    for k in range(n_steps):
        for i, (m, d) in enumerate(zip(models, datas)):
            q = resets[i].get(k)
            if q is not None:
                d.qpos[:] = q
                d.qvel[:] = 0
            u = ctrls[i][k]
            if u is not None:
                d.ctrl[:] = u
            mujoco.mj_step(m, d, nstep=frame_skip)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="mug")
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--steps", type=int, default=400, help="loop iterations (each steps every env)")
    parser.add_argument("--reps", type=int, default=3)
    args = parser.parse_args()
    configure_threads(1)
    config = load_config(overrides=[f"env.object={args.object}", f"actor.envs_per_actor={args.envs}", "actor.random_steps=0"])
    service = ActorService(config, "bench")
    meta = policy_metadata(config, (256, 256))
    service.policy = Policy(Actor(meta.obs_dim, meta.act_dim, meta.hidden), meta, seed=0)
    service.policy_version = 1
    frame_skip = service.envs[0].frame_skip
    print(f"{args.object}: {args.envs} envs x {args.steps} iterations x {args.reps} reps, policy 77-256-256-14, "
          f"frame_skip {frame_skip}, one core", flush=True)
    actor_rates, raw_rates = [], []
    for rep in range(args.reps):
        # A-B-B-A: the actor, the raw physics twice (same controls), the actor again.
        t_actor1, ctrls, resets = record(service, args.steps)
        service.outbox.waiting.clear()
        t_raw = raw([env.model for env in service.envs], ctrls, resets, frame_skip)
        t_raw += raw([env.model for env in service.envs], ctrls, resets, frame_skip)
        t_actor2, _, _ = record(service, args.steps)
        service.outbox.waiting.clear()
        total = 2 * args.steps * args.envs
        actor_rates.append(total / (t_actor1 + t_actor2))
        raw_rates.append(total / t_raw)
        print(f"  rep {rep + 1}/{args.reps}: actor {actor_rates[-1]:6.0f} env steps/s   raw physics {raw_rates[-1]:6.0f} "
              f"env steps/s   ratio {actor_rates[-1] / raw_rates[-1]:.1%}", flush=True)
    a, r = np.median(actor_rates), np.median(raw_rates)
    print(f"median: actor {a:.0f} env steps/s = {a / r:.1%} of the raw physics rate of its envs ({r:.0f}/s)")


if __name__ == "__main__":
    main()
