"""The checks a grasp label must pass, each a small simulation or distance query.

A goal grasp must be a *grasp* (the paper's "both stable and functional"), not a fingertip touch:

- :func:`hold_check`: with the servos at Gg and the object at its nominal pose, hold 1 s on the
  table: the functional finger still touches the functional part, nothing penetrates more than
  2 mm, the object moves less than 1 cm;
- :func:`lift_check`: the same with the table taken away (its contacts off): the hand alone must
  keep the object within 1 cm of where it sits relative to the palm, with the thumb and at least
  two other fingers in contact;
- :func:`pregrasp_clearance`: at G0 no hand geom touches the object for any placement in the
  ±jitter square (so no placement has to be excluded), and the palm is about 2 cm or more from
  the object's surface at the nominal placement;
- :func:`pregrasp_palm_error`: at G0 the palm is inside the env's palm tolerance of its goal for
  every placement in the square (else an episode would fail at its first step).
"""

from __future__ import annotations

import itertools

import mujoco
import numpy as np

from forcegrasp.objects import ObjectSpec
from forcegrasp.scene import SceneIndex, build_model, part_geoms, resting_height

FINGERS = ("ff", "mf", "rf", "lf", "th")
HOLD_LIMIT_M = 0.01  # the object may move this much (on the table, or relative to the palm in the air)
PENETRATION_LIMIT_M = 0.002
PALM_CLEARANCE_M = 0.02  # the paper: the pre-grasp palm ~2 cm from the object's surface
PALM_TOLERANCE_M = 0.1  # the env fails an episode whose palm is farther than this from its goal
PALM_MARGIN_M = 0.005  # what the pre-grasp keeps from that limit at the worst placement


def finger_of_body(m: mujoco.MjModel, body: int) -> str | None:
    """``ff``/``mf``/``rf``/``lf``/``th`` for a finger segment's body, ``palm`` for the palm, else None."""
    name = m.body(body).name
    if name.startswith(FINGERS):
        return name[:2]
    if name in ("palm", "lfmetacarpal"):
        return "palm"
    return None


def place(m, d, ix: SceneIndex, q, offset=(0.0, 0.0), rest_z: float | None = None) -> None:
    """Hand at ``q`` (servos holding it), object upright at rest at ``offset``; no kinematics run."""
    d.qpos[:] = 0
    d.qpos[ix.all_qpos] = q
    d.qpos[ix.object_qpos:ix.object_qpos + 2] = offset
    d.qpos[ix.object_qpos + 2] = resting_height(m) if rest_z is None else rest_z
    d.qpos[ix.object_qpos + 3] = 1.0
    d.ctrl[ix.base_act] = q[:6]
    d.ctrl[ix.hand_act] = q[6:]


def _contacts(m, d, ix: SceneIndex) -> tuple[set[str], float]:
    """Which fingers (and the palm) touch the object now, and the deepest hand-object penetration."""
    hand, objg = set(ix.hand_geoms.tolist()), set(ix.object_geoms.tolist())
    touching, depth = set(), 0.0
    for c in d.contact[: d.ncon] if d.ncon else []:
        for g_hand, g_obj in ((c.geom1, c.geom2), (c.geom2, c.geom1)):
            if g_hand in hand and g_obj in objg:
                finger = finger_of_body(m, m.geom_bodyid[g_hand])
                if finger is not None:
                    touching.add(finger)
                depth = max(depth, -float(c.dist))
    return touching, depth


def _functional_gap(m, d, ix: SceneIndex, obj: ObjectSpec) -> float:
    """Distance from the functional finger (any phalanx: a finger through a mug's handle works it
    with its middle phalanx) to the functional part (a mesh region: the object's surface inside it)."""
    f = obj.grasp_hint.functional_finger
    segments = [m.geom(f"C_{f}{s}").id for s in ("distal", "middle", "proximal")]
    return min(mujoco.mj_geomDistance(m, d, g, o, 0.05, None)
               for g in segments for p in obj.functional_part for o in part_geoms(m, obj, p))


def _object_in_palm(m, d, ix: SceneIndex) -> np.ndarray:
    palm = m.body("palm").id
    rot = d.xmat[palm].reshape(3, 3)
    return rot.T @ (d.xpos[ix.object_body] - d.xpos[palm])


def hold_check(obj: ObjectSpec, q_goal: np.ndarray, mass_scale: float = 1.0, seconds: float = 1.0,
               table: bool = True, hand_overrides: dict[int, float] | None = None) -> dict:
    """Hold Gg for ``seconds`` (servo targets = Gg). ``table=False`` switches the table's contacts
    off: the hand alone carries the object. ``hand_overrides`` (qpos index in the 30 -> value)
    changes some servo targets, e.g. to open a finger and see the check fail."""
    m = build_model(obj, mass_scale)
    rest_z = resting_height(m)  # where the object sits on the table, before the table goes
    if not table:
        for g in range(m.ngeom):
            if m.geom_bodyid[g] == m.body("table").id:
                m.geom_contype[g] = m.geom_conaffinity[g] = 0
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    q = np.asarray(q_goal, float).copy()
    place(m, d, ix, q, rest_z=rest_z)
    if hand_overrides:
        ctrl = np.concatenate([q[:6], q[6:]])
        for i, v in hand_overrides.items():
            ctrl[i] = v
        d.ctrl[ix.base_act], d.ctrl[ix.hand_act] = ctrl[:6], ctrl[6:]
    mujoco.mj_forward(m, d)
    start_world = d.xpos[ix.object_body].copy()
    start_palm = _object_in_palm(m, d, ix)
    depth = 0.0
    for _ in range(int(round(seconds / m.opt.timestep))):
        mujoco.mj_step(m, d)
        depth = max(depth, _contacts(m, d, ix)[1])
    touching, _ = _contacts(m, d, ix)
    gap = _functional_gap(m, d, ix, obj)
    others = sorted(f for f in touching if f in FINGERS and f != "th")
    return {
        "object_moved_m": float(np.linalg.norm(d.xpos[ix.object_body] - start_world)),
        "object_moved_in_palm_m": float(np.linalg.norm(_object_in_palm(m, d, ix) - start_palm)),
        "max_penetration_m": depth,
        "functional_gap_m": float(gap),
        "functional_contact": bool(gap < 0.001),
        "fingers_in_contact": sorted(touching),
        "thumb_and_two": bool("th" in touching and len(others) >= 2),
    }


def lift_check(obj: ObjectSpec, q_goal: np.ndarray, mass_scale: float = 1.0, **kw) -> dict:
    """:func:`hold_check` without the table; ``holds`` is the verdict."""
    out = hold_check(obj, q_goal, mass_scale, table=False, **kw)
    out["holds"] = bool(out["object_moved_in_palm_m"] < HOLD_LIMIT_M and out["thumb_and_two"])
    return out


def pregrasp_clearance(obj: ObjectSpec, q_pre: np.ndarray, jitter: float = 0.02, grid: int = 5) -> dict:
    """Smallest hand-object distance at G0 over a ``grid`` x ``grid`` square of placements (corners
    included) and the palm's distance to the object at the nominal placement."""
    m = build_model(obj)
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    palm_geoms = [g for g in ix.hand_geoms if finger_of_body(m, m.geom_bodyid[g]) == "palm"]
    rest_z = resting_height(m)  # one settling simulation, not one per placement
    worst, worst_at = np.inf, None
    for dx, dy in itertools.product(np.linspace(-jitter, jitter, grid), repeat=2):
        place(m, d, ix, q_pre, (dx, dy), rest_z)
        mujoco.mj_kinematics(m, d)
        c = min(mujoco.mj_geomDistance(m, d, h, o, 0.2, None) for h in ix.hand_geoms for o in ix.object_geoms)
        if c < worst:
            worst, worst_at = c, (float(dx), float(dy))
    place(m, d, ix, q_pre, rest_z=rest_z)
    mujoco.mj_kinematics(m, d)
    palm = min(mujoco.mj_geomDistance(m, d, h, o, 0.2, None) for h in palm_geoms for o in ix.object_geoms)
    return {"min_clearance_m": float(worst), "worst_offset": worst_at, "palm_distance_m": float(palm),
            "clear": bool(worst > 0.0)}


def pregrasp_palm_error(m: mujoco.MjModel, q_pre: np.ndarray, goal_palm: np.ndarray, jitter: float = 0.02,
                        rest_z: float | None = None) -> dict:
    """The palm's distance from its goal (relative to the object) at G0, at the nominal placement
    and at the worst corner of the ±jitter square (the offset adds at most its length)."""
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    place(m, d, ix, q_pre, rest_z=rest_z)
    mujoco.mj_kinematics(m, d)
    nominal = float(np.linalg.norm(d.site_xpos[ix.palm_site] - d.xpos[ix.object_body] - goal_palm))
    worst = nominal + float(np.hypot(jitter, jitter))
    return {"palm_error_m": nominal, "worst_palm_error_m": worst,
            "within_palm_tolerance": bool(worst < PALM_TOLERANCE_M - PALM_MARGIN_M)}
