"""Env steps/s against raw ``mj_step`` throughput of the same model and frame skip, one core.

The raw loop replays the very control sequence the env produced (random policy, resets
included) with nothing but ``d.ctrl[:] = u; mj_step(m, d, nstep=frame_skip)``, from the env's
full simulator state after each reset (``mj_setState``), so both sides simulate the same
trajectory and contacts and the ratio isolates the env's own Python overhead. (Restoring only
``qpos`` with ``qvel = 0``, as before 2026-12-01, let the raw trajectory drift into other
contacts: on the contact-rich new grasps that alone moved the ratio by 10-15 points.)
The two sides alternate every ``--chunk`` steps (env then raw, raw then env, ...), each chunk's
raw side starting from the env's recorded state there, and the ratio is of the summed times: a
shared machine whose speed drifts by the second hits both sides alike. (Whole A-B-B-A runs of
5,000 steps, as before 2026-12-02, drifted by 76-104 % between repetitions of one command.)

    python bench/bench_env.py --object mug --steps 6000 --reps 3
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np

from forcegrasp.env import FunctionalGraspEnv


STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # everything mj_step reads: positions, velocities, warm start...


def _state(env: FunctionalGraspEnv) -> np.ndarray:
    out = np.empty(mujoco.mj_stateSize(env.model, STATE))
    mujoco.mj_getState(env.model, env.data, out, STATE)
    return out


def record_ctrls(env: FunctionalGraspEnv, actions: np.ndarray, seed: int, chunk: int) -> tuple[np.ndarray, dict, dict]:
    """The env's controls, its full simulator state after every reset, and its state at every chunk
    boundary: replayed from those states, the raw loop simulates exactly the env's trajectory
    (MuJoCo is deterministic), so both sides meet the same contacts."""
    ctrls, resets, boundaries = [], {}, {}
    env.reset(seed=seed)
    resets[0] = _state(env)
    for k, a in enumerate(actions):
        if k % chunk == 0:
            boundaries[k] = _state(env)
        _, _, term, trunc, _ = env.step(a)
        ctrls.append(env.data.ctrl.copy())
        if term or trunc:
            env.reset()
            resets[k + 1] = _state(env)
    return np.array(ctrls), resets, boundaries


def run_raw(m: mujoco.MjModel, d: mujoco.MjData, ctrls: np.ndarray, resets: dict, steps: range, frame_skip: int) -> float:
    """Seconds for the bare loop over ``steps`` (the caller set ``d`` to the state before the first)."""
    t0 = time.perf_counter()
    for k in steps:
        state = resets.get(k)
        if state is not None and k != steps.start:
            mujoco.mj_setState(m, d, state, STATE)
        d.ctrl[:] = ctrls[k]
        mujoco.mj_step(m, d, nstep=frame_skip)
    return time.perf_counter() - t0


def run_env_chunk(env: FunctionalGraspEnv, actions: np.ndarray, steps: range) -> float:
    t0 = time.perf_counter()
    for k in steps:
        _, _, term, trunc, _ = env.step(actions[k])
        if term or trunc:
            env.reset()
    return time.perf_counter() - t0


def interleaved(env: FunctionalGraspEnv, actions, ctrls, resets, boundaries, chunk: int, seed: int) -> tuple[float, float]:
    """(env seconds, raw seconds) over all steps, the sides alternating chunk by chunk."""
    m, d = env.model, mujoco.MjData(env.model)
    t_env = t_raw = 0.0
    env.reset(seed=seed)
    for i, start in enumerate(range(0, len(actions), chunk)):
        steps = range(start, min(len(actions), start + chunk))
        mujoco.mj_setState(m, d, resets.get(start, boundaries[start]), STATE)  # untimed: the env pays no such call
        if i % 2 == 0:
            t_env += run_env_chunk(env, actions, steps)
            t_raw += run_raw(m, d, ctrls, resets, steps, env.frame_skip)
        else:
            t_raw += run_raw(m, d, ctrls, resets, steps, env.frame_skip)
            t_env += run_env_chunk(env, actions, steps)
    return t_env, t_raw


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="mug")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--chunk", type=int, default=100, help="steps per side before they alternate")
    args = parser.parse_args()

    env = FunctionalGraspEnv(args.object)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (args.steps, 7)).astype(np.float32)
    ctrls, resets, boundaries = record_ctrls(env, actions, seed=0, chunk=args.chunk)
    print(f"{args.object}: {args.steps} steps x {args.reps} reps, frame_skip {env.frame_skip}, "
          f"{len(resets)} episodes per run, sides alternating every {args.chunk} steps")
    env_rates, raw_rates = [], []
    for rep in range(args.reps):
        t_env, t_raw = interleaved(env, actions, ctrls, resets, boundaries, args.chunk, seed=0)
        env_rates.append(args.steps / t_env)
        raw_rates.append(args.steps / t_raw)
        print(f"  rep {rep + 1}/{args.reps}: env {env_rates[-1]:7.0f} steps/s   raw mj_step {raw_rates[-1]:7.0f} steps/s"
              f"   ratio {env_rates[-1] / raw_rates[-1]:.1%}", flush=True)
    ratios = np.array(env_rates) / np.array(raw_rates)
    e, r = np.median(env_rates), np.median(raw_rates)
    print(f"median: env {e:.0f} steps/s, raw {r:.0f} steps/s ({r * env.frame_skip:.0f} physics steps/s); "
          f"env runs at {np.median(ratios):.1%} of the raw physics rate (repetitions {ratios.min():.1%}-{ratios.max():.1%})")


if __name__ == "__main__":
    main()
