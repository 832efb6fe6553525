"""Running observation statistics (``learner.sac.obs_norm``), frozen into every policy file."""

from __future__ import annotations

import numpy as np


class RunningMeanStd:
    """Mean and variance of every observation dimension over all data seen (Chan et al.'s
    parallel update, float64). ``std`` has a floor so constant inputs stay finite."""

    STD_FLOOR = 1e-3

    def __init__(self, dim: int):
        self.count, self.mean, self.var = 0.0, np.zeros(dim), np.ones(dim)

    def update(self, x: np.ndarray) -> None:
        n = x.shape[0]
        if n == 0:
            return
        mean, var = x.mean(0), x.var(0)
        total = self.count + n
        delta = mean - self.mean
        m2 = self.var * self.count + var * n + delta**2 * self.count * n / total
        self.mean = self.mean + delta * n / total
        self.var, self.count = m2 / total, total

    def std(self) -> np.ndarray:
        return np.maximum(np.sqrt(self.var), self.STD_FLOOR)

    def state(self) -> dict[str, np.ndarray]:
        return {"count": np.array(self.count), "mean": self.mean.copy(), "var": self.var.copy()}

    def load(self, state: dict) -> None:
        self.count, self.mean, self.var = float(state["count"]), np.array(state["mean"], np.float64), np.array(
            state["var"], np.float64)
