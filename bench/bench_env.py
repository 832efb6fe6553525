"""Env steps/s against raw ``mj_step`` throughput of the same model and frame skip, one core.

The raw loop replays the very control sequence the env produced (random policy, resets
included) with nothing but ``d.ctrl[:] = u; mj_step(m, d, nstep=frame_skip)``, from the env's
full simulator state after each reset (``mj_setState``), so both sides simulate the same
trajectory and contacts and the ratio isolates the env's own Python overhead. (Restoring only
``qpos`` with ``qvel = 0``, as before 2026-12-01, let the raw trajectory drift into other
contacts: on the contact-rich new grasps that alone moved the ratio by 10-15 points.)
Each repetition runs env, raw, raw, env (A-B-B-A) so a drifting machine hits both alike.

    python bench/bench_env.py --object mug --steps 3000 --reps 3
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np

from forcegrasp.env import FunctionalGraspEnv


def run_env(env: FunctionalGraspEnv, actions: np.ndarray, seed: int):
    """Step the env through ``actions`` (resetting at episode ends); returns seconds and resets."""
    starts = []
    env.reset(seed=seed)
    starts.append((0, env.data.qpos.copy(), env.data.ctrl.copy()))
    t0 = time.perf_counter()
    for k, a in enumerate(actions):
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset()
            starts.append((k + 1, env.data.qpos.copy(), env.data.ctrl.copy()))
    elapsed = time.perf_counter() - t0
    return elapsed, starts


STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # everything mj_step reads: positions, velocities, warm start...


def _state(env: FunctionalGraspEnv) -> np.ndarray:
    out = np.empty(mujoco.mj_stateSize(env.model, STATE))
    mujoco.mj_getState(env.model, env.data, out, STATE)
    return out


def record_ctrls(env: FunctionalGraspEnv, actions: np.ndarray, seed: int) -> tuple[np.ndarray, list]:
    """The env's controls and the full simulator state after every reset: replayed from those
    states, the raw loop simulates exactly the env's trajectory (MuJoCo is deterministic), so both
    sides meet the same contacts."""
    ctrls, starts = [], []
    env.reset(seed=seed)
    starts.append((0, _state(env)))
    for k, a in enumerate(actions):
        _, _, term, trunc, _ = env.step(a)
        ctrls.append(env.data.ctrl.copy())
        if term or trunc:
            env.reset()
            starts.append((k + 1, _state(env)))
    return np.array(ctrls), starts


def run_raw(m: mujoco.MjModel, ctrls: np.ndarray, starts: list, frame_skip: int) -> float:
    d = mujoco.MjData(m)
    resets = dict(starts)
    t0 = time.perf_counter()
    for k in range(len(ctrls)):
        state = resets.get(k)
        if state is not None:
            mujoco.mj_setState(m, d, state, STATE)
        d.ctrl[:] = ctrls[k]
        mujoco.mj_step(m, d, nstep=frame_skip)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="mug")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--reps", type=int, default=3)
    args = parser.parse_args()

    env = FunctionalGraspEnv(args.object)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (args.steps, 7)).astype(np.float32)
    ctrls, starts = record_ctrls(env, actions, seed=0)
    print(f"{args.object}: {args.steps} steps x {args.reps} reps, frame_skip {env.frame_skip}, "
          f"{len(starts)} episodes per run")
    env_rates, raw_rates = [], []
    for rep in range(args.reps):
        # A-B-B-A: a machine whose speed drifts during a repetition hits both sides alike.
        t_env1, _ = run_env(env, actions, seed=0)
        t_raw = run_raw(env.model, ctrls, starts, env.frame_skip) + run_raw(env.model, ctrls, starts, env.frame_skip)
        t_env2, _ = run_env(env, actions, seed=0)
        env_rates.append(2 * args.steps / (t_env1 + t_env2))
        raw_rates.append(2 * args.steps / t_raw)
        print(f"  rep {rep + 1}/{args.reps}: env {env_rates[-1]:7.0f} steps/s   raw mj_step {raw_rates[-1]:7.0f} steps/s"
              f"   ratio {env_rates[-1] / raw_rates[-1]:.1%}", flush=True)
    e, r = np.median(env_rates), np.median(raw_rates)
    print(f"median: env {e:.0f} steps/s, raw {r:.0f} steps/s ({r * env.frame_skip:.0f} physics steps/s), "
          f"env runs at {e / r:.1%} of the raw physics rate")


if __name__ == "__main__":
    main()
