"""n-step returns, built where the trajectory is whole: in the actor, one accumulator per env.

A transition (s_t, a_t) leaves with R = sum_{k<h} gamma^k r_{t+k}, the state s_{t+h} to bootstrap
from and its horizon h (the learner discounts the bootstrap by gamma^h). h = n inside an episode;
at its end every pending transition leaves with the steps that remain: after a termination with
``terminated`` set (no bootstrap), after a truncation (the step limit) with the true last state
and ``terminated`` clear, so the learner still bootstraps from it. With n = 1 this is the plain
one-step transition. Entropy bonuses of the intermediate steps are not included, as in other
n-step SAC implementations.
"""

from __future__ import annotations

import collections
from typing import Any, NamedTuple

import numpy as np


class NStepTransition(NamedTuple):
    obs: np.ndarray
    action: np.ndarray
    reward: float  # the discounted sum of up to n rewards
    next_obs: np.ndarray  # the state `horizon` steps later (the last one at an episode's end)
    terminated: bool
    truncated: bool
    horizon: int
    extra: Any = None  # travels with obs (e.g. privileged state)
    next_extra: Any = None  # travels with next_obs


class NStepAccumulator:
    """One env's stream of one-step transitions in, n-step transitions out (see module doc)."""

    def __init__(self, n: int, gamma: float):
        if int(n) < 1:
            raise ValueError(f"n-step horizon must be >= 1, got {n}")
        if not 0.0 <= float(gamma) <= 1.0:
            raise ValueError(f"gamma must lie in [0, 1], got {gamma}")
        self.n, self.gamma = int(n), float(gamma)
        self._pending: collections.deque = collections.deque()

    def __len__(self) -> int:
        return len(self._pending)

    def push(self, obs, action, reward, next_obs, terminated: bool, truncated: bool, extra=None,
             next_extra=None) -> list[NStepTransition]:
        """Add the step (s_t, a_t, r_t, s_t+1); returns the transitions that are now complete."""
        self._pending.append((obs, action, float(reward), extra))
        out = []
        if terminated or truncated:
            while self._pending:
                out.append(self._emit(next_obs, next_extra, bool(terminated), bool(truncated)))
        elif len(self._pending) == self.n:
            out.append(self._emit(next_obs, next_extra, False, False))
        return out

    def _emit(self, next_obs, next_extra, terminated: bool, truncated: bool) -> NStepTransition:
        ret = 0.0
        for k, (_, _, r, _) in enumerate(self._pending):
            ret += self.gamma**k * r
        horizon = len(self._pending)
        obs, action, _, extra = self._pending.popleft()
        return NStepTransition(obs, action, ret, next_obs, terminated, truncated, horizon, extra, next_extra)
