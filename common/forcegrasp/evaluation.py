"""Deterministic policy evaluation on fixed, jittered placements (the paper's test protocol).

Every checkpoint is scored on the *same* placements: the object offsets and episode seeds come
from ``run.seed`` and a stream name alone, so two checkpoints differ only by their policy. The
policy acts deterministically (tanh of the mean), the env is deterministic for a given seed and
offset, so a score is reproducible: a restarted evaluator, or a final ranking computed for one
checkpoint and cached, gives the same number as a fresh run.

Streams: ``"eval"`` (``evaluator.eval_episodes`` placements, the periodic test), ``"rank"``
(``evaluator.final_rank_episodes`` placements, the final selection among the top k), and ``"test"``
(``forcegrasp eval``: held out from any selection).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

STREAMS = {"eval": 1, "rank": 2, "test": 3}


class Interrupted(Exception):
    """The service is stopping: the evaluation in progress is abandoned (and redone on restart)."""


@dataclass(frozen=True)
class Placement:
    index: int
    seed: int
    offset: tuple[float, float]


def placements(seed: int, count: int, jitter: float, stream: str = "eval",
               clear: Callable[[tuple[float, float]], bool] | None = None) -> list[Placement]:
    """``count`` object offsets uniform in ``[-jitter, jitter]^2`` and episode seeds, fixed by
    ``(seed, stream)``: the first ``n`` placements do not depend on ``count``.

    ``clear`` (e.g. `FunctionalGraspEnv.is_clear`) keeps only offsets where the pre-grasp hand
    does not start inside the object, the distribution random resets draw from.
    """
    from forcegrasp.env import draw_clear_offset

    rng = np.random.default_rng(np.random.SeedSequence([int(seed), STREAMS[stream]]))
    out = []
    for i in range(int(count)):
        dx, dy = draw_clear_offset(rng, jitter, clear)
        out.append(Placement(i, int(rng.integers(0, 2**31 - 1)), (float(dx), float(dy))))
    return out


@dataclass
class EpisodeResult:
    index: int
    seed: int
    offset: tuple[float, float]
    ret: float
    length: int
    success: bool
    failure: str | None


@dataclass
class EvalResult:
    """Score of one policy on one set of placements: ``score`` is the mean undiscounted return."""

    score: float
    success_rate: float
    episodes: int
    steps: int = 0
    seconds: float = 0.0
    returns: list[float] = field(default_factory=list)
    conditions: dict = field(default_factory=dict)  # per test condition, when several were mixed
    objects: dict = field(default_factory=dict)  # per object, when several were scored (forcegrasp.multi_object)

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def of(cls, results: list[EpisodeResult], seconds: float = 0.0) -> "EvalResult":
        if not results:
            raise ValueError("no episodes")
        returns = [r.ret for r in results]
        return cls(score=float(np.mean(returns)), success_rate=float(np.mean([r.success for r in results])),
                   episodes=len(results), steps=sum(r.length for r in results), seconds=seconds, returns=returns)


def run_episode(env, policy, placement: Placement, logger=None) -> EpisodeResult:
    """One deterministic episode from ``placement``; ``logger`` is an :class:`EpisodeLogger` or None."""
    obs, info = env.reset(seed=placement.seed, options={"offset": placement.offset})
    if logger is not None:
        logger.begin(placement.seed, info)
    ret, length = 0.0, 0
    try:
        while True:
            action = policy(obs)
            obs, reward, terminated, truncated, info = env.step(action)
            ret += reward
            length += 1
            if logger is not None:
                logger.step(action, reward, info)
            if terminated or truncated:
                break
    except BaseException:
        if logger is not None:
            logger.abort()
        raise
    result = EpisodeResult(placement.index, placement.seed, placement.offset, float(ret), length,
                           bool(info["success"]), info["failure"])
    if logger is not None:
        logger.end(result.ret, result.length, result.success, result.failure)
    return result


def evaluate(env, policy, places: list[Placement], *, log_dir: Path | None = None, log_prefix: str = "ep",
             log_metadata: dict | None = None, should_stop: Callable[[], bool] | None = None,
             on_episode: Callable[[EpisodeResult], None] | None = None, logger_backend: str = "auto") -> EvalResult:
    """Run ``policy`` on every placement; with ``log_dir`` each episode goes to ``<prefix>-<i>.mcap``.

    ``should_stop`` is checked between episodes and raises :class:`Interrupted` when it says so.
    """
    from forcegrasp.mcap_log import EpisodeLogger

    t0 = time.perf_counter()
    results = []
    for p in places:
        if should_stop is not None and should_stop():
            raise Interrupted()
        logger = None
        if log_dir is not None:
            meta = {**(log_metadata or {}), "episode": p.index, "stream": log_prefix}
            logger = EpisodeLogger(Path(log_dir) / f"{log_prefix}-{p.index:03d}.mcap", env, meta, backend=logger_backend)
        results.append(run_episode(env, policy, p, logger))
        if on_episode is not None:
            on_episode(results[-1])
    return EvalResult.of(results, time.perf_counter() - t0)
