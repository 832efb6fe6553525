"""The paper's reward and terminal tests (section V of ``functional-grasp-force-feedback.tex``),
as pure functions of a state: unit-testable, and importable without the simulator.

r = w + wa ra + wb rb + wc rc with ra = -|1 - h|, rb = -||p - p_g|| (palm relative to the current
object position vs. its goal), rc = -||T_c - T~|| (object displacement from its jittered start).
Success (|rc| < 0.01, |ra| < 0.05, |rb| < 0.01) adds 1000 + 1.5 (200 - step); moving the object
beyond ``object_tolerance`` or the palm beyond ``palm_tolerance`` fails.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RewardWeights:
    w: float = 1.5
    wa: float = 1.0
    wb: float = 20.0
    wc: float = 100.0
    success_bonus: float = 1000.0
    step_bonus: float = 1.5


@dataclass(frozen=True)
class Outcome:
    """The paper's reward terms and terminal tests for one state (pure: unit-testable)."""

    r_a: float
    r_b: float
    r_c: float
    reward: float
    success: bool
    failure: str | None


def observed_h(joint_angles: np.ndarray, goal_angles: np.ndarray, joint_range: np.ndarray) -> float:
    """h = 1 - 0.5 max_i |j_i - j_i^g| with each difference normalised by the joint's range."""
    return 1.0 - 0.5 * float((np.abs(joint_angles - goal_angles) / joint_range).max())


def evaluate_state(
    h: float,
    palm_rel: np.ndarray,
    goal_palm_rel: np.ndarray,
    object_pos: np.ndarray,
    object_start: np.ndarray,
    step: int,
    max_steps: int = 200,
    weights: RewardWeights = RewardWeights(),
    object_tolerance: float = 0.01,
    palm_tolerance: float = 0.1,
    success_tolerances: tuple[float, float, float] = (0.01, 0.05, 0.01),
) -> Outcome:
    """Reward terms, success and failure for a state; ``step`` counts from 1."""
    r_a = -abs(1.0 - h)
    palm_error = palm_rel - goal_palm_rel
    displacement = object_pos - object_start
    r_b = -math.sqrt(float(palm_error.dot(palm_error)))  # np.linalg.norm costs 5x more here
    r_c = -math.sqrt(float(displacement.dot(displacement)))
    reward = weights.w + weights.wa * r_a + weights.wb * r_b + weights.wc * r_c
    tol_c, tol_a, tol_b = success_tolerances
    success = -r_c < tol_c and -r_a < tol_a and -r_b < tol_b
    failure = None
    if success:
        reward += weights.success_bonus + weights.step_bonus * (max_steps - step)
    elif -r_c > object_tolerance:
        failure = "object_moved"
    elif -r_b > palm_tolerance:
        failure = "palm_deviation"
    return Outcome(r_a, r_b, r_c, reward, success, failure)
