"""Grasp labels as data: the pre-grasp G0 and the goal functional grasp Gg of one object.

A grasp G = (T, R, J): T and R are the hand base's 6 driving-joint values (3 slides, 3 hinges)
and J the 24 hand-joint angles, all with the object at its nominal pose (its frame at the
table origin). The base slides translate the hand rigidly, so for an object displaced by a
world vector d the same grasp is reached with T + S^T d (S: the slides' world axes, see
``GraspLabel.shift``). ``goal_palm`` is the palm point (site S_grasp) relative to the object
at the goal: the paper's p_g.

File: ``assets/labels/<object>.json`` written by ``forcegrasp label OBJECT``.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from forcegrasp import ASSETS_DIR
from forcegrasp.scene import BASE_JOINTS, HAND_JOINTS

LABEL_FORMAT = 1


class LabelFileError(ValueError):
    """A label file is missing or malformed (the message names the field)."""


@dataclass(frozen=True)
class Grasp:
    base: np.ndarray  # (6,) T (3 slides, m) and R (3 hinges, rad)
    hand: np.ndarray  # (24,) J, in HAND_JOINTS order

    @property
    def q(self) -> np.ndarray:
        return np.concatenate([self.base, self.hand])


@dataclass(frozen=True)
class GraspLabel:
    object: str
    pregrasp: Grasp
    goal: Grasp
    goal_palm: np.ndarray  # (3,) palm relative to the object at the goal
    checks: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        def grasp(g: Grasp) -> dict:
            return {
                "base": dict(zip(BASE_JOINTS, map(float, g.base))),
                "hand": dict(zip(HAND_JOINTS, map(float, g.hand))),
            }

        return {
            "format": LABEL_FORMAT,
            "object": self.object,
            "pregrasp": grasp(self.pregrasp),
            "goal": grasp(self.goal),
            "goal_palm": [float(v) for v in self.goal_palm],
            "checks": self.checks,
        }


def labels_dir() -> Path:
    return ASSETS_DIR / "labels"


def label_path(object_name: str) -> Path:
    return labels_dir() / f"{object_name}.json"


def _joint_map(raw, names, what: str, source: str) -> np.ndarray:
    if not isinstance(raw, dict):
        raise LabelFileError(f"{source}: field {what!r} must be a map joint -> value")
    missing = [n for n in names if n not in raw]
    extra = [k for k in raw if k not in names]
    if missing or extra:
        raise LabelFileError(f"{source}: field {what!r} missing joints {missing} / unknown joints {extra}")
    try:
        values = np.array([float(raw[n]) for n in names])
    except (TypeError, ValueError):
        raise LabelFileError(f"{source}: field {what!r} has a non-numeric value") from None
    if not np.all(np.isfinite(values)):
        raise LabelFileError(f"{source}: field {what!r} has a non-finite value")
    return values


def parse_label(raw, source: str = "<label>") -> GraspLabel:
    if not isinstance(raw, dict):
        raise LabelFileError(f"{source}: a label file must hold a JSON object")
    if raw.get("format") != LABEL_FORMAT:
        raise LabelFileError(f"{source}: field 'format' must be {LABEL_FORMAT}, got {raw.get('format')!r}")
    for key in ("object", "pregrasp", "goal", "goal_palm"):
        if key not in raw:
            raise LabelFileError(f"{source}: missing field {key!r}")
    grasps = {}
    for key in ("pregrasp", "goal"):
        g = raw[key]
        if not isinstance(g, dict) or "base" not in g or "hand" not in g:
            raise LabelFileError(f"{source}: field {key!r} must have 'base' and 'hand'")
        grasps[key] = Grasp(
            base=_joint_map(g["base"], BASE_JOINTS, f"{key}.base", source),
            hand=_joint_map(g["hand"], HAND_JOINTS, f"{key}.hand", source),
        )
    try:
        palm = np.array(raw["goal_palm"], dtype=float)
    except (TypeError, ValueError):
        palm = np.zeros(0)
    if palm.shape != (3,) or not np.all(np.isfinite(palm)):
        raise LabelFileError(f"{source}: field 'goal_palm' must be 3 finite numbers, got {raw['goal_palm']!r}")
    return GraspLabel(
        object=str(raw["object"]),
        pregrasp=grasps["pregrasp"],
        goal=grasps["goal"],
        goal_palm=palm,
        checks=dict(raw.get("checks", {})),
    )


def load_label(object_name: str, path: Path | None = None) -> GraspLabel:
    path = Path(path) if path is not None else label_path(object_name)
    if not path.is_file():
        raise LabelFileError(f"no grasp label for {object_name!r} at {path}; run `forcegrasp label {object_name}`")
    try:
        raw = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise LabelFileError(f"{path}: not readable JSON ({exc})") from exc
    label = parse_label(raw, source=str(path))
    if label.object != object_name:
        raise LabelFileError(f"{path}: field 'object' is {label.object!r}, expected {object_name!r}")
    return label


def save_label(label: GraspLabel, path: Path | None = None) -> Path:
    """Write atomically (temp file + rename) so a crash never leaves half a label."""
    path = Path(path) if path is not None else label_path(label.object)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(label.to_json(), f, indent=2)
        f.write("\n")
    os.replace(tmp, path)
    return path


__all__ = ["Grasp", "GraspLabel", "LabelFileError", "load_label", "save_label", "parse_label"]
