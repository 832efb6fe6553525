"""A success-gated curriculum for domain randomisation: open the ranges as the policy copes.

Torque noise drawn from the first episode stalls learning (a policy that has never found the grasp
cannot yet learn to ignore a noisy sensor), so an actor can start every env at its fixed training
conditions (`env.mass_scale`, `env.torque_noise_std`: level 0) and open the randomisation ranges
(`env.mass_scale_range`, `env.torque_noise_range`, `env.jitter_range`) one step at a time, each time its last
``window`` policy episodes succeeded at least ``threshold`` of the time (the gate of automatic
domain randomisation, OpenAI 2019, reduced to one level for all ranges). The level never falls:
a run ends trained on the full ranges if it ever copes with them. Each actor keeps its own level;
every episode's draws reach the asymmetric critic (`forcegrasp.task.PRIVILEGED_LAYOUT` "domain").
"""

from __future__ import annotations

from collections import deque


class RandomisationCurriculum:
    """The level (0..1) of an actor's envs: ``record`` each ended policy episode's success."""

    def __init__(self, threshold: float, window: int, steps: int):
        if not 0.0 < threshold <= 1.0 or window < 1 or steps < 1:
            raise ValueError(f"curriculum needs 0 < threshold <= 1, window >= 1, steps >= 1; got "
                             f"{threshold!r}, {window!r}, {steps!r}")
        self.threshold, self.window, self.steps = float(threshold), int(window), int(steps)
        self.stage = self.episodes = 0
        self._recent: deque[bool] = deque(maxlen=self.window)

    @property
    def level(self) -> float:
        return self.stage / self.steps

    def record(self, success: bool) -> bool:
        """Count one policy episode; True when this opened the next stage (a fresh window starts)."""
        self.episodes += 1
        if self.stage >= self.steps:
            return False
        self._recent.append(bool(success))
        if len(self._recent) < self.window or sum(self._recent) < self.threshold * self.window:
            return False
        self.stage += 1
        self._recent.clear()
        return True
