"""One policy for several objects: which env steps which object, and how per-object scores combine.

A run trains several objects with one learner and one replay buffer when ``env.objects`` is set
(empty: ``env.object`` alone). Every object's observation has the same size and says which object
it is through its label's goal pose and goal palm position, so the policy gets no other object input.

- **Assignment** (`assign_objects`): env ``j`` of actor ``i`` steps ``objects[(i * envs_per_actor + j) %
  len(objects)]``, so the actors' envs go round the object set in turn: every actor steps every
  object when ``envs_per_actor >= len(objects)``, and with fewer envs the actors' objects follow on
  from each other (actor 0 the first objects, actor 1 the next ...). ``i`` is the number of an id
  ``actor-<i>`` (what ``forcegrasp up`` names its actors; ``actor-<i>.<host>`` too), else a stable
  hash of the id (compose replicas: a spread in expectation). An actor on a spare machine for one
  object is started with ``--set env.objects='["power_drill"]'``: its object set is a part of the run's.
- **Adaptive sampling** (``env.object_sampling = "adaptive"``, a lever reported apart): the assignment
  above picks each env's first object only; every later episode's object is drawn by
  `AdaptiveObjectSampler` from the actor's own recent success, so objects it fails get more episodes
  (the worst object decides a generalist's score, see Evaluation). Demonstrations stay on the
  assigned object.
- **Transitions** carry the object they came from (``objects`` names and a ``u8`` ``object_index``
  per transition and per ended episode, docs/protocol.md): for statistics, never a policy input. The
  learner drops, counts and logs a batch naming an object outside its run's set.
- **Evaluation** (`mix_objects`): a checkpoint is scored on every object (under every test
  condition, mixed by their mean per object); its score is the aggregate ``evaluator.object_aggregate``
  over objects of the per-object scores: ``min`` by default (a policy is as good as its worst
  object) or ``mean``. Success rates aggregate the same way, separately from the scores.
- **Policy files** of a multi-object run have ``object_name`` "" and ``extra["objects"]`` the set.
"""

from __future__ import annotations

import re
import zlib
from collections import deque
from typing import Callable, Mapping, Sequence

import numpy as np

AGGREGATES = ("min", "mean")
SAMPLING = ("fixed", "adaptive")
MAX_OBJECTS = 255  # the wire's object index is one byte


def run_objects(env) -> list[str]:
    """The objects of a run (an `EnvConfig`): ``env.objects``, or ``[env.object]``."""
    return list(env.objects) or [env.object]


def actor_index(actor_id: str) -> int:
    """``actor-3`` (or ``actor-3.host7``) -> 3; any other id -> a stable hash of it (crc32)."""
    m = re.fullmatch(r"actor-(\d+)(?:\..*)?", str(actor_id))
    return int(m.group(1)) if m else zlib.crc32(str(actor_id).encode())


def assign_objects(objects: Sequence[str], envs_per_actor: int, index: int) -> list[str]:
    """The object of each env of actor number ``index`` (see the module docstring)."""
    if not objects:
        raise ValueError("no objects to assign")
    return [objects[(index * envs_per_actor + j) % len(objects)] for j in range(envs_per_actor)]


class AdaptiveObjectSampler:
    """Draws the next episode's object: ``p = (1 - mix) / K + mix * (1 - s_o) / sum(1 - s)``, where
    ``s_o`` is the success over the last ``window`` policy episodes of object ``o`` (0 before any).
    The uniform part keeps every object in the data (no forgetting of the solved ones); the rest goes
    to the objects that still fail, in proportion to how often they fail. All solved: uniform."""

    def __init__(self, objects: Sequence[str], rng: np.random.Generator, window: int = 50, mix: float = 0.5):
        if not objects:
            raise ValueError("no objects to sample")
        self.objects = list(objects)
        self.rng = rng
        self.mix = mix
        self.recent = {o: deque(maxlen=window) for o in self.objects}

    def record(self, name: str, success: bool) -> None:
        self.recent[name].append(bool(success))

    def probabilities(self) -> np.ndarray:
        fail = np.array([1.0 - (np.mean(r) if r else 0.0) for r in self.recent.values()])
        uniform = np.full(len(self.objects), 1.0 / len(self.objects))
        if fail.sum() <= 0:
            return uniform
        return (1.0 - self.mix) * uniform + self.mix * fail / fail.sum()

    def draw(self) -> str:
        return self.objects[int(self.rng.choice(len(self.objects), p=self.probabilities()))]


def policy_objects(meta) -> list[str]:
    """The objects a policy was trained on: ``extra["objects"]``, else its ``object_name`` (may be [])."""
    recorded = meta.extra.get("objects")
    if isinstance(recorded, list) and recorded and all(isinstance(o, str) and o for o in recorded):
        return list(recorded)
    return [meta.object_name] if meta.object_name else []


def check_objects(meta, objects: Sequence[str]) -> None:
    """ValueError when a policy records another object set than ``objects`` (one recording none fits)."""
    trained = policy_objects(meta)
    if trained and sorted(trained) != sorted(objects):
        raise ValueError(f"policy was trained on {', '.join(trained)}, this run on {', '.join(objects)}")


def aggregate(values: Sequence[float], how: str = "min") -> float:
    if how not in AGGREGATES:
        raise ValueError(f"object aggregate must be one of {', '.join(AGGREGATES)}, got {how!r}")
    if not values:
        raise ValueError("no per-object values to aggregate")
    return float(min(values)) if how == "min" else float(sum(values) / len(values))


def mix_objects(parts: Mapping, how: str = "min"):
    """One `EvalResult` from each object's: score and success rate aggregated across objects
    (each on its own), episodes, steps and seconds summed, each object's figures in ``objects``."""
    from forcegrasp.evaluation import EvalResult

    results = list(parts.values())
    return EvalResult(score=aggregate([r.score for r in results], how),
                      success_rate=aggregate([r.success_rate for r in results], how),
                      episodes=sum(r.episodes for r in results), steps=sum(r.steps for r in results),
                      seconds=sum(r.seconds for r in results), returns=[x for r in results for x in r.returns],
                      objects={o: {"score": r.score, "success_rate": r.success_rate, "episodes": r.episodes,
                                   **({"conditions": r.conditions} if r.conditions else {})}
                               for o, r in parts.items()})


def object_table(objects: Mapping[str, Mapping], how: str | None = None) -> list[str]:
    """A Markdown table of per-object figures (``{object: {score, success_rate, episodes}}``)."""
    lines = ["| object | success | mean return | episodes |", "|---|---:|---:|---:|"]
    for name, v in objects.items():
        lines.append(f"| {name} | {v['success_rate']:.0%} | {v['score']:.1f} | {v['episodes']} |")
    if how is not None and objects:
        rows = list(objects.values())
        lines.append(f"| {how} over objects | {aggregate([r['success_rate'] for r in rows], how):.0%} | "
                     f"{aggregate([r['score'] for r in rows], how):.1f} | {sum(r['episodes'] for r in rows)} |")
    return lines


def score_grid(score_one: Callable, objects: Sequence, conditions: Sequence, how: str = "min"):
    """A checkpoint's `EvalResult` over objects x test conditions: ``score_one(object, condition)``
    scores one pair (``[None]``: the run's one object, or its own env settings); per object the
    conditions mix by their plain mean (`forcegrasp.conditions.mix`, each condition's figures kept in
    ``conditions``), across objects by `mix_objects` with the aggregate ``how``."""
    from forcegrasp.conditions import ConditionScore, mix
    from forcegrasp.evaluation import EvalResult

    def for_object(obj):
        parts = {c: score_one(obj, c) for c in conditions}
        if list(conditions) == [None]:
            return parts[None]
        m = mix({c: ConditionScore(r.score, r.success_rate, r.episodes) for c, r in parts.items()})
        return EvalResult(score=m.score, success_rate=m.success_rate, episodes=m.episodes,
                          steps=sum(r.steps for r in parts.values()), seconds=sum(r.seconds for r in parts.values()),
                          returns=[x for r in parts.values() for x in r.returns],
                          conditions={c: {"score": r.score, "success_rate": r.success_rate, "episodes": r.episodes}
                                      for c, r in parts.items()})

    if list(objects) == [None]:
        return for_object(None)
    return mix_objects({o: for_object(o) for o in objects}, how)
