"""A scripted controller for FunctionalGrasp: the solvability check and the no-feedback baseline.

It plays the label's straight approach through the env's own action interface: first the
base slides the pre-grasp over to where it *believes* the object is (h stays 0), then base
and h move together along a straight joint-space line to the goal, then it holds.
Told the true offset it shows the task is solvable; blind (offset assumed zero) it shows
what an open-loop approach achieves, which is the gap force feedback has to close.
"""

from __future__ import annotations

import numpy as np

from forcegrasp.env import FunctionalGraspEnv, draw_clear_offset


class ScriptedApproach:
    def __init__(self, env: FunctionalGraspEnv, believed_offset=(0.0, 0.0), shift_steps: int = 20, approach_steps: int = 60):
        self.env = env
        label = env.label
        shift = env.goal_base_for_offset(believed_offset) - label.goal.base
        self.waypoints = [
            (label.pregrasp.base + shift, 0.0, shift_steps),
            (label.goal.base + shift, 1.0, approach_steps),
        ]
        self.start_base = label.pregrasp.base.copy()
        self.scale = env._action_scale
        self.k = 0

    def _plan(self, k: int) -> tuple[np.ndarray, float]:
        base, h = self.start_base, 0.0
        for target_base, target_h, n in self.waypoints:
            if k <= n:
                s = k / n
                return base + s * (target_base - base), h + s * (target_h - h)
            k -= n
            base, h = target_base, target_h
        return base, h

    def __call__(self, obs=None) -> np.ndarray:
        self.k += 1
        base, h = self._plan(self.k)
        env = self.env
        delta = np.concatenate([base - env.base_target, [h - env.h_command]])
        return np.clip(delta / self.scale, -1.0, 1.0).astype(np.float32)


def run_episode(env: FunctionalGraspEnv, offset, told: bool, seed: int | None = None) -> dict:
    """One scripted episode at a given object offset; returns the final info and the return."""
    env.reset(seed=seed, options={"offset": offset})
    controller = ScriptedApproach(env, believed_offset=offset if told else (0.0, 0.0))
    total, info = 0.0, {}
    while True:
        _, reward, terminated, truncated, info = env.step(controller())
        total += reward
        if terminated or truncated:
            return {**info, "return": total}


def success_rate(env: FunctionalGraspEnv, offsets, told: bool) -> tuple[float, list[dict]]:
    results = [run_episode(env, off, told) for off in offsets]
    return float(np.mean([r["success"] for r in results])), results


def jitter_offsets(n: int, jitter: float = 0.02, seed: int = 0, env: FunctionalGraspEnv | None = None) -> np.ndarray:
    """``n`` offsets uniform in the ±jitter square; with `env`, only those it can start from (`is_clear`)."""
    rng = np.random.default_rng(seed)
    return np.array([draw_clear_offset(rng, jitter, env.is_clear if env else None) for _ in range(n)]).reshape(n, 2)
