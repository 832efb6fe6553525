"""Named test conditions: the paper's robustness experiments as env settings, and their mix.

A grasp policy is judged on more than the conditions it trained in. Each condition is a set of
`FunctionalGraspEnv` keywords applied on top of a policy's own env (object, observation, action
steps); randomisation ranges are never on in a test, so every episode of a condition is fixed by its
placement. The evaluator ranks checkpoints on the mean of its conditions' scores
(``evaluator.conditions``), and ``forcegrasp experiment`` tests its marks on each of them.

=============  ==============================================================================
``5x``         the paper's training conditions: 5x mass, 1 cm movement tolerance, no noise, ±2 cm
``1x_3cm``     the object's own mass, 3 cm movement tolerance (the paper's Fig. 7)
``0.5x_3cm``   half its mass, 3 cm movement tolerance (Fig. 7)
``1x_1cm``     its own mass with the strict 1 cm tolerance of training
``0.5x_1cm``   half its mass with the strict 1 cm tolerance
``noise_0.5``  5x mass, Gaussian joint-torque noise of 0.5 N·m (Fig. 8's middle)
``jitter_3cm`` 5x mass, object jittered within ±3 cm instead of ±2 cm
=============  ==============================================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping

#: Each condition's env keywords (fixed values: a test condition never randomises).
CONDITIONS: dict[str, dict] = {
    "5x": {"mass_scale": 5.0},
    "1x_3cm": {"mass_scale": 1.0, "object_tolerance": 0.03},
    "0.5x_3cm": {"mass_scale": 0.5, "object_tolerance": 0.03},
    "1x_1cm": {"mass_scale": 1.0},
    "0.5x_1cm": {"mass_scale": 0.5},
    "noise_0.5": {"mass_scale": 5.0, "torque_noise_std": 0.5},
    "jitter_3cm": {"mass_scale": 5.0, "jitter": 0.03},
}
#: The mix a robust policy is selected and tested on: every experiment of issue-level interest.
ROBUST_MIX = ("5x", "1x_3cm", "0.5x_3cm", "noise_0.5", "jitter_3cm")
#: Every condition keyword an env takes from a test condition.
_FIXED = {"mass_scale_range": None, "torque_noise_range": None, "jitter_range": None}


def check_conditions(names: Iterable[str], what: str = "conditions") -> list[str]:
    """The names as a list, or ValueError naming the unknown one and the known ones."""
    names = list(names)
    for name in names:
        if name not in CONDITIONS:
            raise ValueError(f"{what}: unknown condition {name!r} (known: {', '.join(CONDITIONS)})")
    if len(set(names)) != len(names):
        raise ValueError(f"{what}: {names} names a condition twice")
    return names


def env_kwargs(name: str, base: Mapping | None = None) -> dict:
    """FunctionalGraspEnv keywords of a condition on top of ``base`` (no randomisation)."""
    return {**(base or {}), **_FIXED, **CONDITIONS[check_conditions([name])[0]]}


@dataclass(frozen=True)
class ConditionScore:
    score: float         # mean return
    success_rate: float
    episodes: int


def mix(scores: Mapping[str, ConditionScore]) -> ConditionScore:
    """The mixed score: the plain mean of the conditions' scores and success rates (each condition
    weighs the same whatever its episode count), episodes summed."""
    if not scores:
        raise ValueError("no condition scores to mix")
    n = len(scores)
    return ConditionScore(sum(s.score for s in scores.values()) / n,
                          sum(s.success_rate for s in scores.values()) / n,
                          sum(s.episodes for s in scores.values()))
