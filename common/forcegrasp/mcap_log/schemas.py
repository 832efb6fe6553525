"""The JSON schemas of the episode logs' channels and the topics they go on."""

from __future__ import annotations

import json
from typing import Any, Iterable


from forcegrasp.scene import ALL_JOINTS


METADATA_NAME = "forcegrasp.episode"
PER_STEP_TOPICS = ("/tf", "/joint_states", "/command", "/reward")
ONCE_TOPICS = ("/scene", "/outcome")
WORLD = "world"
PALM_FRAME = "palm_center"
OBJECT_FRAME = "object"

dumps = json.JSONEncoder(separators=(",", ":"), check_circular=False, allow_nan=False).encode


# --------------------------------------------------------------------------------------------
# JSON schemas: compact subsets of Foxglove's well-known schemas (the fields written here), and
# ForceGrasp's own. Foxglove matches well-known schemas by name.
# --------------------------------------------------------------------------------------------

def _obj(props: dict, required: Iterable[str] | None = None, title: str | None = None) -> dict:
    out: dict[str, Any] = {"type": "object", "properties": props}
    out["required"] = list(props) if required is None else list(required)
    if title:
        out["title"] = title
    return out


_NUM = {"type": "number"}
_INT = {"type": "integer"}
_STR = {"type": "string"}
_BOOL = {"type": "boolean"}
_TIME = _obj({"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
             title="time")
_VEC3 = _obj({"x": _NUM, "y": _NUM, "z": _NUM}, title="foxglove.Vector3")
_POINT3 = _obj({"x": _NUM, "y": _NUM, "z": _NUM}, title="foxglove.Point3")
_QUAT = _obj({"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM}, title="foxglove.Quaternion")
_POSE = _obj({"position": _VEC3, "orientation": _QUAT}, title="foxglove.Pose")
_COLOR = _obj({"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM}, title="foxglove.Color")


def _array(items: dict, n: int | None = None) -> dict:
    out: dict[str, Any] = {"type": "array", "items": items}
    if n is not None:
        out["minItems"] = out["maxItems"] = n
    return out


SCHEMAS: dict[str, dict] = {
    "foxglove.FrameTransforms": _obj({"transforms": _array(_obj({
        "timestamp": _TIME, "parent_frame_id": _STR, "child_frame_id": _STR,
        "translation": _VEC3, "rotation": _QUAT}, title="foxglove.FrameTransform"))}),
    "foxglove.JointStates": _obj({"timestamp": _TIME, "joints": _array(_obj({
        "name": _STR, "position": _NUM, "effort": _NUM}, required=["name"],
        title="foxglove.JointState"))}),
    "foxglove.SceneUpdate": _obj({"deletions": _array(_obj({"timestamp": _TIME, "type": _INT, "id": _STR})),
                                  "entities": _array(_obj({
        "timestamp": _TIME, "frame_id": _STR, "id": _STR,
        "lifetime": _obj({"sec": _INT, "nsec": _INT}, title="duration"),
        "frame_locked": _BOOL,
        "metadata": _array(_obj({"key": _STR, "value": _STR}, title="foxglove.KeyValuePair")),
        "cubes": _array(_obj({"pose": _POSE, "size": _VEC3, "color": _COLOR}, title="foxglove.CubePrimitive")),
        "spheres": _array(_obj({"pose": _POSE, "size": _VEC3, "color": _COLOR}, title="foxglove.SpherePrimitive")),
        "cylinders": _array(_obj({"pose": _POSE, "size": _VEC3, "bottom_scale": _NUM, "top_scale": _NUM,
                                  "color": _COLOR}, title="foxglove.CylinderPrimitive")),
        "triangles": _array(_obj({"pose": _POSE, "points": _array(_POINT3), "color": _COLOR, "colors": _array(_COLOR),
                                  "indices": _array(_INT)}, title="foxglove.TriangleListPrimitive")),
    }, required=["timestamp", "frame_id", "id", "frame_locked"], title="foxglove.SceneEntity"))},
        required=["entities"]),
    "forcegrasp.Command": _obj({
        "timestamp": _TIME, "step": _INT,
        "action": _array(_NUM, 7),
        "targets": _array(_NUM, len(ALL_JOINTS)), "h_command": _NUM,
    }),
    "forcegrasp.RewardTerms": _obj({
        "timestamp": _TIME, "step": _INT, "reward": _NUM, "r_a": _NUM, "r_b": _NUM, "r_c": _NUM, "h": _NUM,
        "object_displacement": _NUM, "palm_error": _NUM, "return": _NUM, "success": _BOOL,
        "failure": {"type": ["string", "null"]},
    }),
    "forcegrasp.EpisodeOutcome": _obj({
        "timestamp": _TIME, "return": _NUM, "length": _INT, "success": _BOOL,
        "failure": {"type": ["string", "null"]}, "seed": _INT, "offset": _array(_NUM, 2),
    }),
}
for _name, _schema in SCHEMAS.items():
    _schema["title"] = _name
    _schema["$comment"] = "ForceGrasp episode log (common/forcegrasp/mcap_log/); the fields ForceGrasp writes"

TOPIC_SCHEMAS = {
    "/scene": "foxglove.SceneUpdate",
    "/tf": "foxglove.FrameTransforms",
    "/joint_states": "foxglove.JointStates",
    "/command": "forcegrasp.Command",
    "/reward": "forcegrasp.RewardTerms",
    "/outcome": "forcegrasp.EpisodeOutcome",
}
