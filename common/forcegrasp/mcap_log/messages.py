"""Building the logs' messages: the scene once, the per-step topics as fixed-width JSON by numpy."""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass

import mujoco
import numpy as np

from forcegrasp.scene import ALL_JOINTS, REGION_GROUP, VISUAL_GROUP
from forcegrasp.mcap_log.schemas import OBJECT_FRAME, SCHEMAS, WORLD, dumps


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------

def time_stamp(t_ns: int) -> dict:
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


def _quat_wxyz_to_dict(q) -> dict:
    return {"x": q[1], "y": q[2], "z": q[3], "w": q[0]}


def _pose(pos, quat_wxyz) -> dict:
    return {"position": {"x": pos[0], "y": pos[1], "z": pos[2]}, "orientation": _quat_wxyz_to_dict(quat_wxyz)}


def _color(rgba) -> dict:
    r, g, b, a = (round(float(c), 4) for c in rgba)
    return {"r": r, "g": g, "b": b, "a": a}


@dataclass
class _Frames:
    """Which bodies get a transform each step, precomputed once per model."""

    bodies: np.ndarray            # body ids, hand bodies then the object
    names: list[str]              # their frame names
    geoms: dict[int, list[int]]   # body id -> visual geoms (collision capsules/boxes, object primitives)


def frames_of(m: mujoco.MjModel, ix) -> _Frames:
    hand_bodies = sorted({int(m.geom_bodyid[g]) for g in ix.hand_geoms})
    bodies = hand_bodies + [int(ix.object_body)]
    names = [f"hand/{m.body(b).name}" for b in hand_bodies] + [OBJECT_FRAME]
    geoms: dict[int, list[int]] = {b: [] for b in bodies}
    drawn_object = [g for g in range(m.ngeom) if m.geom_bodyid[g] == ix.object_body]  # a mesh's visual too
    for g in list(ix.hand_geoms) + drawn_object:
        geoms[int(m.geom_bodyid[g])].append(int(g))
    return _Frames(np.array(bodies), names, geoms)


def _geom_primitives(m: mujoco.MjModel, g: int) -> dict[str, list]:
    """Foxglove primitives for one MuJoCo geom, in its body's frame (capsule = cylinder + 2 spheres)."""
    gtype, size = int(m.geom_type[g]), [float(s) for s in m.geom_size[g]]
    pos, quat = m.geom_pos[g].tolist(), m.geom_quat[g].tolist()
    color = _color(m.geom_rgba[g] if m.geom_rgba[g][3] > 0 else (0.7, 0.7, 0.7, 1.0))
    pose = _pose(pos, quat)
    T = mujoco.mjtGeom
    if gtype == T.mjGEOM_BOX:
        return {"cubes": [{"pose": pose, "size": {"x": 2 * size[0], "y": 2 * size[1], "z": 2 * size[2]}, "color": color}]}
    if gtype == T.mjGEOM_SPHERE:
        d = 2 * size[0]
        return {"spheres": [{"pose": pose, "size": {"x": d, "y": d, "z": d}, "color": color}]}
    if gtype == T.mjGEOM_ELLIPSOID:
        return {"spheres": [{"pose": pose, "size": {"x": 2 * size[0], "y": 2 * size[1], "z": 2 * size[2]}, "color": color}]}
    if gtype in (T.mjGEOM_CYLINDER, T.mjGEOM_CAPSULE):
        d, length = 2 * size[0], 2 * size[1]
        out = {"cylinders": [{"pose": pose, "size": {"x": d, "y": d, "z": length}, "bottom_scale": 1.0,
                              "top_scale": 1.0, "color": color}]}
        if gtype == T.mjGEOM_CAPSULE:  # hemispherical caps at +-half-length along the geom's z axis
            axis = np.zeros(3)
            mujoco.mju_rotVecQuat(axis, np.array([0.0, 0.0, size[1]]), m.geom_quat[g])
            out["spheres"] = [{"pose": _pose((m.geom_pos[g] + s * axis).tolist(), quat),
                               "size": {"x": d, "y": d, "z": d}, "color": color} for s in (1.0, -1.0)]
        return out
    if gtype == T.mjGEOM_MESH and int(m.geom_group[g]) in (VISUAL_GROUP, REGION_GROUP):  # not the collision parts
        mesh = int(m.geom_dataid[g])
        v0, nv = int(m.mesh_vertadr[mesh]), int(m.mesh_vertnum[mesh])
        f0, nf = int(m.mesh_faceadr[mesh]), int(m.mesh_facenum[mesh])
        points = [{"x": x, "y": y, "z": z} for x, y, z in np.round(m.mesh_vert[v0:v0 + nv], 5).tolist()]
        return {"triangles": [{"pose": pose, "points": points, "color": color, "colors": [],
                               "indices": m.mesh_face[f0:f0 + nf].ravel().tolist()}]}
    return {}  # planes and the hand's visual meshes (its collision primitives are drawn): not drawn


# --------------------------------------------------------------------------------------------
# Fixed-width JSON: the per-step messages are built by numpy, not by json.dumps
# --------------------------------------------------------------------------------------------
#
# JSON allows whitespace around a number, so every number can take a fixed-width slot
# ("  -1.234567 ": sign and 3 integer digits right-aligned in 4 columns, a point, 6 decimals,
# a space). With fixed-width slots a message is a constant byte template: per step, numpy turns
# all of the step's numbers into characters at once (three lookups in tables of 4-character
# groups, no per-number Python call) and copies them into the template's columns. That is ~5x
# cheaper than formatting ~260 numbers one by one, and keeps MCAP logging within the evaluator's
# overhead budget. A step with a value outside (-1000, 1000) (never seen: forces are capped at
# 400 N) or not finite takes the slow path (json.dumps, NaN/inf as null).

FLOAT_WIDTH = 12
FIXED_LIMIT = 999.9999994
_F, _S, _I = "\x01", "\x02", "\x03"  # template markers: a float slot, the stamp slot, an integer slot
STAMP_FMT = b'{"sec":%10d,"nsec":%10d}'
INT_FMT = b"%10d"
_WIDTHS = {_F: FLOAT_WIDTH, _S: len(STAMP_FMT % (0, 0)), _I: len(INT_FMT % 0)}


def _groups(texts: list[str]) -> np.ndarray:
    """4-character strings as one little-endian uint32 each (a lookup moves 4 bytes at once)."""
    return np.frombuffer("".join(texts).encode(), np.uint8).view("<u4").copy()


_WHOLE = _groups([f"{i:4d}" for i in range(1000)] + [f"{'-' + str(i):>4}" for i in range(1000)])
_POINT_3 = _groups([f".{i:03d}" for i in range(1000)])
_3_SPACE = _groups([f"{i:03d} " for i in range(1000)])


def fixed_chars(values: np.ndarray) -> np.ndarray:
    """``(n, 12)`` ASCII of ``values`` (|v| <= FIXED_LIMIT, finite) with 6 decimals."""
    scaled = np.rint(np.abs(values) * 1e6).astype(np.int64)
    whole, frac = np.divmod(scaled, 1_000_000)
    high, low = np.divmod(frac, 1000)
    out = np.empty((len(values), 3), "<u4")
    out[:, 0] = _WHOLE[whole + 1000 * ((values < 0) & (scaled > 0))]  # never "-0.000000"
    out[:, 1] = _POINT_3[high]
    out[:, 2] = _3_SPACE[low]
    return out.view(np.uint8)


#: /reward, one step: floats at full precision (str of a Python float is its shortest repr).
REWARD_FMT = ('{"timestamp":{"sec":%d,"nsec":%d},"step":%d,"reward":%s,"r_a":%s,"r_b":%s,"r_c":%s,"h":%s,'
               '"object_displacement":%s,"palm_error":%s,"return":%s,"success":%s,"failure":%s}')


class _FixedMessage:
    """A JSON message with fixed-width slots (see ``fixed_chars``), filled for many steps at once.

    ``text`` is the message with one marker character per slot: ``_F`` a float, ``_S`` the
    timestamp object, ``_I`` an integer. Filling produces a ``(steps, length)`` byte array.
    """

    def __init__(self, text: str):
        out, slots, pos = [], {_F: [], _S: [], _I: []}, 0
        for ch in text:
            if ch in slots:
                slots[ch].append(pos)
                ch = " " * _WIDTHS[ch]
            out.append(ch)
            pos += len(ch)
        self.template = np.frombuffer("".join(out).encode(), np.uint8)
        self.n_floats = len(slots[_F])
        self.float_idx = (np.array(slots[_F], dtype=np.intp)[:, None] + np.arange(FLOAT_WIDTH)).ravel()
        self.stamp_cols, self.int_cols = slots[_S], slots[_I]

    def fill(self, chars: np.ndarray, stamps: np.ndarray, ints: np.ndarray) -> np.ndarray:
        """``chars`` ``(steps, n_floats, 12)``, ``stamps`` ``(steps, 36)``, ``ints`` ``(steps, 10)``."""
        rows = np.empty((len(chars), len(self.template)), np.uint8)
        rows[:] = self.template
        rows[:, self.float_idx] = chars.reshape(len(chars), -1)
        for col in self.stamp_cols:
            rows[:, col:col + stamps.shape[1]] = stamps
        for col in self.int_cols:
            rows[:, col:col + ints.shape[1]] = ints
        return rows


@functools.lru_cache(maxsize=8)
def templates(frame_names: tuple[str, ...]) -> tuple[_FixedMessage, _FixedMessage, _FixedMessage]:
    """The fixed-width ``/tf``, ``/joint_states`` and ``/command`` messages (built once)."""
    xyz = '{"x":%s,"y":%s,"z":%s' % (_F, _F, _F)
    tf = _FixedMessage('{"transforms":[' + ",".join(
        '{"timestamp":' + _S + ',"parent_frame_id":' + json.dumps(WORLD) + ',"child_frame_id":' + json.dumps(name)
        + ',"translation":' + xyz + '},"rotation":' + xyz + ',"w":' + _F + "}}" for name in frame_names) + "]}")
    joints = _FixedMessage('{"timestamp":' + _S + ',"joints":[' + ",".join(
        '{"name":' + json.dumps(name) + ',"position":' + _F + ',"effort":' + _F + "}" for name in ALL_JOINTS) + "]}")
    command = _FixedMessage('{"timestamp":' + _S + ',"step":' + _I + ',"action":[' + ",".join([_F] * 7)
                            + '],"targets":[' + ",".join([_F] * len(ALL_JOINTS)) + '],"h_command":' + _F + "}")
    return tf, joints, command


SCHEMA_BYTES = {name: json.dumps(schema).encode() for name, schema in SCHEMAS.items()}
SCENE_STAMP = '{"sec":0,"nsec":1}'  # placeholder replaced by each episode's start time


_SCENES: dict[int, tuple[mujoco.MjModel, str]] = {}  # id(model) -> (model kept alive, JSON)


def scene_json(m: mujoco.MjModel, ix, object_name: str) -> str:
    """``/scene`` for a model (built once): one entity per body frame, carrying its geoms."""
    cached = _SCENES.get(id(m))
    if cached is not None and cached[0] is m:
        return cached[1]
    if len(_SCENES) >= 8:
        _SCENES.clear()
    frames = frames_of(m, ix)
    stamp = json.loads(SCENE_STAMP)
    entities = []
    for body, frame in zip(frames.bodies, frames.names):
        entity = {"timestamp": stamp, "frame_id": frame, "id": frame, "lifetime": {"sec": 0, "nsec": 0},
                  "frame_locked": True, "metadata": [], "cubes": [], "spheres": [], "cylinders": [], "triangles": []}
        for g in frames.geoms[int(body)]:
            for kind, prims in _geom_primitives(m, g).items():
                entity[kind].extend(prims)
        if frame == OBJECT_FRAME:
            entity["metadata"] = [{"key": "object", "value": object_name}]
        entities.append(entity)
    text = dumps({"deletions": [], "entities": entities})
    _SCENES[id(m)] = (m, text)
    return text
