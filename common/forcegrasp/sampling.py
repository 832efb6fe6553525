"""What random resets draw: the object's placement in the jitter square and a randomisation
range's bounds. One rule for training resets, evaluation placements and the scripted benches."""

from __future__ import annotations

import numpy as np

MAX_OFFSET_DRAWS = 100


def span(name: str, values, *, positive: bool) -> tuple[float, float] | None:
    """A randomisation range as (low, high), or None when off (None or empty)."""
    if values is None or len(values) == 0:
        return None
    if len(values) != 2:
        raise ValueError(f"{name} must be (low, high), got {values!r}")
    low, high = (float(x) for x in values)
    if not (np.isfinite(low) and np.isfinite(high) and (low > 0 if positive else low >= 0) and low <= high):
        raise ValueError(f"{name} must be (low, high) with {'0 <' if positive else '0 <='} low <= high, got {values!r}")
    return low, high


def draw_clear_offset(rng: np.random.Generator, jitter: float, is_clear=None, what: str = "the object") -> np.ndarray:
    """An offset (dx, dy) uniform in the ±jitter square, redrawn while ``is_clear(offset)`` says no:
    the one sampling rule of random resets, evaluation placements and the scripted benches."""
    for _ in range(MAX_OFFSET_DRAWS):
        offset = rng.uniform(-jitter, jitter, 2)
        if is_clear is None or is_clear(offset):
            return offset
    raise RuntimeError(f"{what}: the pre-grasp hand overlaps the object at {MAX_OFFSET_DRAWS} random offsets "
                       "in a row; relabel the pre-grasp")


def draw(rng: np.random.Generator, nominal: float, full: tuple[float, float] | None, level: float, *,
         log: bool = False) -> float:
    """This episode's value: ``nominal`` without a range (no draw), else uniform (log-uniform with
    ``log``) in the part of the range ``level`` has opened (`widened`)."""
    if full is None:
        return float(nominal)
    low, high = widened(nominal, full, level, log=log)
    return float(np.exp(rng.uniform(np.log(low), np.log(high)))) if log else float(rng.uniform(low, high))


def widened(nominal: float, full: tuple[float, float], level: float, *, log: bool = False) -> tuple[float, float]:
    """The part of a randomisation range a curriculum has opened: each bound moves from ``nominal``
    (level 0: the fixed training value) to the full range's bound (level 1), in log space for a
    scale such as mass."""
    f = (np.log, np.exp) if log else (float, float)
    lo, hi = (f[1](f[0](nominal) + level * (f[0](bound) - f[0](nominal))) for bound in full)
    return float(min(lo, hi)), float(max(lo, hi))
