"""Grasp labelling: find the goal functional grasp by optimisation, derive the pre-grasp by search.

Goal grasp Gg: nonlinear least squares (``mujoco.minimize.least_squares``) over the 30 joint
values, with the object at its nominal pose. Residuals, each a signed distance from
``mj_geomDistance`` after ``mj_kinematics``:
- the functional finger's distal phalanx touches the functional part (gap -> -1 mm: the servo then presses);
- each support fingertip touches the object (gap -> 0), and the palm too where the object's
  hint asks for a power grasp (``palm_contact``);
- no hand geom penetrates the object or the table (penalty on depth beyond 1.2 mm);
- a small pull towards the start pose keeps the posture natural.

Pre-grasp G0: candidates open the fingers part-way from Jg and back the palm off by 2-4 cm
(along its normal, back along the forearm, upwards, or a mix); the first candidate with no contact at G0 (clearance >= 5 mm) whose straight
J = h(Jg - J0) + J0 sweep, played by the scripted controller at the nominal placement, succeeds
in the task's own terms is kept.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import mujoco
import numpy as np
from mujoco import minimize

from forcegrasp.labels import Grasp, GraspLabel
from forcegrasp.objects import ObjectSpec
from forcegrasp.scene import (
    ALL_JOINTS,
    HAND_JOINTS,
    SceneIndex,
    build_model,
    object_geom_name,
    resting_height,
    slide_axes,
)

FLEXION_JOINTS = tuple(j for j in HAND_JOINTS if j[-1] in "012" and j[:2] != "WR")
CONTACT_TARGET = -0.001  # m: aiming 1 mm into the part makes the servo press on it
PENETRATION_FREE = 0.0012  # m of depth tolerated before the penalty starts


@dataclass
class GoalProblem:
    m: mujoco.MjModel
    d: mujoco.MjData
    ix: SceneIndex
    functional_geom: int
    part_geoms: list[int]
    support_geoms: list[int]
    palm_geom: int
    palm_contact: bool
    table_geom: int
    q_start: np.ndarray
    w_functional: float = 100.0
    w_contact: float = 10.0
    w_penetration: float = 300.0
    w_posture: float = 0.03

    def residual_one(self, q: np.ndarray) -> np.ndarray:
        m, d, ix = self.m, self.d, self.ix
        d.qpos[ix.all_qpos] = q
        mujoco.mj_kinematics(m, d)
        dist = lambda a, b: mujoco.mj_geomDistance(m, d, a, b, 0.2, None)  # noqa: E731
        gap = min(dist(self.functional_geom, g) for g in self.part_geoms)
        res = [self.w_functional * (gap - CONTACT_TARGET)]
        for tip in self.support_geoms:
            res.append(self.w_contact * min(dist(tip, g) for g in ix.object_geoms))
        if self.palm_contact:
            res.append(self.w_contact * min(dist(self.palm_geom, g) for g in ix.object_geoms))
        for h in ix.hand_geoms:
            for o in (*ix.object_geoms, self.table_geom):
                depth = -dist(h, o)
                res.append(self.w_penetration * max(0.0, depth - PENETRATION_FREE))
        res.extend(self.w_posture * (q - self.q_start))
        return np.asarray(res)

    def residual(self, x: np.ndarray) -> np.ndarray:
        return np.stack([self.residual_one(x[:, i]) for i in range(x.shape[1])], axis=1)


def _start_pose(obj: ObjectSpec, m: mujoco.MjModel, ix: SceneIndex) -> np.ndarray:
    q = np.zeros(len(ALL_JOINTS))
    q[3:6] = obj.grasp_hint.rotation
    for name, value in obj.grasp_hint.fingers.items():
        if name not in ALL_JOINTS:
            raise ValueError(f"{obj.name}: grasp_hint.fingers names unknown joint {name!r}")
        q[ALL_JOINTS.index(name)] = value
    for j in FLEXION_JOINTS:  # a loosely curled hand is a better start than a flat one
        if j not in obj.grasp_hint.fingers:
            q[ALL_JOINTS.index(j)] = 0.4
    # Slide the base so the palm centre sits at the hinted point (slides translate rigidly).
    d = mujoco.MjData(m)
    d.qpos[ix.all_qpos] = q
    mujoco.mj_kinematics(m, d)
    q[:3] = slide_axes(m).T @ (np.asarray(obj.grasp_hint.palm_at) - d.site_xpos[ix.palm_site])
    return np.clip(q, ix.all_range[:, 0], ix.all_range[:, 1])


def solve_goal(obj: ObjectSpec, m: mujoco.MjModel | None = None, seed: int = 0, restarts: int = 4, log=print):
    """Best goal grasp over a few perturbed starts: (q (30,), residual cost, problem)."""
    m = m if m is not None else build_model(obj)
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    hint = obj.grasp_hint
    problem = GoalProblem(
        m=m,
        d=d,
        ix=ix,
        functional_geom=ix.fingertip_geoms[hint.functional_finger],
        part_geoms=[m.geom(object_geom_name(obj, p)).id for p in obj.functional_part],
        support_geoms=[ix.fingertip_geoms[f] for f in hint.support_fingers],
        palm_geom=m.geom("C_palm0").id,
        palm_contact=hint.palm_contact,
        table_geom=_table_geom(m),
        q_start=_start_pose(obj, m, ix),
    )
    d.qpos[ix.object_qpos + 2] = resting_height(m)
    d.qpos[ix.object_qpos + 3] = 1.0
    rng = np.random.default_rng(seed)
    lo, hi = ix.all_range[:, 0], ix.all_range[:, 1]
    best = None
    for attempt in range(restarts):
        x0 = problem.q_start.copy()
        if attempt:
            x0[:3] += rng.normal(0, 0.01, 3)
            x0[3:6] += rng.normal(0, 0.05, 3)
            x0[6:] += rng.normal(0, 0.1, 24)
        x0 = np.clip(x0, lo, hi)
        x, _ = minimize.least_squares(x0, problem.residual, bounds=(lo, hi), max_iter=80, verbose=0, output=io.StringIO())
        cost = float(np.sum(problem.residual_one(x)[: -len(x)] ** 2))
        log(f"  start {attempt + 1}/{restarts}: contact+penetration cost {cost:.3e}")
        if best is None or cost < best[1]:
            best = (x, cost)
        if cost < 1e-4:
            break
    return best[0], best[1], problem


def _table_geom(m: mujoco.MjModel) -> int:
    table = m.body("table").id
    return next(g for g in range(m.ngeom) if m.geom_bodyid[g] == table and m.geom_contype[g])


def hand_object_clearance(m, d, ix: SceneIndex) -> float:
    """Smallest signed distance between any hand geom and the object (negative = penetration)."""
    return min(mujoco.mj_geomDistance(m, d, h, o, 0.1, None) for h in ix.hand_geoms for o in ix.object_geoms)


def pregrasp_candidates(m: mujoco.MjModel, q_goal: np.ndarray):
    """Yield (opening fraction, retreat distance, direction name, q0), nearest candidates first.

    The palm backs off along its normal, back along the forearm, or upwards (or a mix): which
    one sweeps cleanly depends on how the fingers enclose the part, so the search tries them.
    """
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    d.qpos[ix.all_qpos] = q_goal
    d.qpos[ix.object_qpos + 3] = 1.0
    mujoco.mj_kinematics(m, d)
    normal = palm_normal_world(m, d, ix)
    back = -finger_direction_world(m, d)
    up = np.array([0.0, 0.0, 1.0])
    directions = {
        "palm normal": -normal,
        "back": back,
        "up": up,
        "back+up": back + up,
        "normal+up": -normal + up,
        "normal+back": -normal + back,
    }
    flex = np.array([ALL_JOINTS.index(j) for j in FLEXION_JOINTS])
    S = slide_axes(m)
    for retreat in (0.02, 0.03, 0.04):
        for name, direction in directions.items():
            direction = direction / np.linalg.norm(direction)
            for opening in (0.3, 0.6, 0.9):
                q0 = q_goal.copy()
                q0[flex] = q_goal[flex] * (1.0 - opening)
                q0[:3] = q_goal[:3] + S.T @ (direction * retreat)
                yield opening, retreat, name, np.clip(q0, ix.all_range[:, 0], ix.all_range[:, 1])


def finger_direction_world(m, d) -> np.ndarray:
    """Unit vector from the wrist towards the middle finger's knuckle."""
    return _unit(d.xpos[m.body("mfknuckle").id] - d.xpos[m.body("palm").id])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def palm_normal_world(m, d, ix: SceneIndex) -> np.ndarray:
    """Unit vector the palm faces: -z of the palm body (fingers curl towards it)."""
    palm = m.body("palm").id
    return -d.xmat[palm].reshape(3, 3)[:, 1]


def goal_palm_of(m: mujoco.MjModel, q_goal: np.ndarray) -> np.ndarray:
    """Palm centre relative to the object (at the origin) at the goal grasp: the paper's p_g."""
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    d.qpos[ix.all_qpos] = q_goal
    d.qpos[ix.object_qpos + 2] = resting_height(m)
    d.qpos[ix.object_qpos + 3] = 1.0
    mujoco.mj_kinematics(m, d)
    return d.site_xpos[ix.palm_site] - d.xpos[ix.object_body]


def hold_check(obj: ObjectSpec, q_goal: np.ndarray, mass_scale: float = 1.0, seconds: float = 1.0) -> dict:
    """Hold the goal grasp (servo targets = Gg) for ``seconds`` with gravity, object at nominal.

    Returns the object's displacement, the deepest hand-object penetration seen and whether the
    functional finger touches the functional part at the end.
    """
    m = build_model(obj, mass_scale)
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    d.qpos[ix.all_qpos] = q_goal
    d.qpos[ix.object_qpos + 2] = resting_height(m)
    d.qpos[ix.object_qpos + 3] = 1.0
    d.ctrl[ix.base_act] = q_goal[:6]
    d.ctrl[ix.hand_act] = q_goal[6:]
    mujoco.mj_forward(m, d)
    start = d.xpos[ix.object_body].copy()
    hand = set(ix.hand_geoms.tolist())
    objg = set(ix.object_geoms.tolist())
    functional = ix.fingertip_geoms[obj.grasp_hint.functional_finger]
    parts = {m.geom(object_geom_name(obj, p)).id for p in obj.functional_part}
    depth = 0.0
    for _ in range(int(round(seconds / m.opt.timestep))):
        mujoco.mj_step(m, d)
        for c in d.contact[: d.ncon] if d.ncon else []:
            if (c.geom1 in hand and c.geom2 in objg) or (c.geom2 in hand and c.geom1 in objg):
                depth = max(depth, -float(c.dist))
    gap = min(mujoco.mj_geomDistance(m, d, functional, p, 0.05, None) for p in parts)
    return {
        "object_moved_m": float(np.linalg.norm(d.xpos[ix.object_body] - start)),
        "max_penetration_m": depth,
        "functional_gap_m": float(gap),
        "functional_contact": bool(gap < 0.001),
    }


def label_object(obj: ObjectSpec, mass_scale: float = 5.0, seed: int = 0, log=print) -> GraspLabel:
    """Goal by optimisation, pre-grasp by search, checks recorded in the label."""
    from forcegrasp.env import FunctionalGraspEnv
    from forcegrasp.scripted import run_episode

    m = build_model(obj)
    log(f"[1/3] goal grasp for {obj.name}: least squares over 30 joints")
    q_goal, cost, _ = solve_goal(obj, m, seed=seed, log=log)
    goal = Grasp(base=q_goal[:6].copy(), hand=q_goal[6:].copy())
    goal_palm = goal_palm_of(m, q_goal)

    log("[2/3] pre-grasp: search over finger opening and palm retreat")
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    rest_z = resting_height(m)
    chosen = None
    for opening, retreat, direction, q0 in pregrasp_candidates(m, q_goal):
        d.qpos[:] = 0
        d.qpos[ix.all_qpos] = q0
        d.qpos[ix.object_qpos + 2] = rest_z
        d.qpos[ix.object_qpos + 3] = 1.0
        mujoco.mj_kinematics(m, d)
        clearance = hand_object_clearance(m, d, ix)
        what = f"  {direction:>11}, retreat {retreat * 100:.0f} cm, opening {opening:.1f}:"
        if clearance < 0.005:
            log(f"{what} clearance {clearance * 1000:.1f} mm, rejected")
            continue
        label = GraspLabel(obj.name, Grasp(q0[:6].copy(), q0[6:].copy()), goal, goal_palm)
        env = FunctionalGraspEnv(obj.name, mass_scale=mass_scale, label=label)
        result = run_episode(env, (0.0, 0.0), told=True)
        log(
            f"{what} clearance {clearance * 1000:.1f} mm, "
            f"nominal approach {'succeeds' if result['success'] else 'fails (' + str(result['failure']) + ')'}"
        )
        if result["success"]:
            chosen = (opening, retreat, direction, q0, clearance, result)
            break
    if chosen is None:
        raise RuntimeError(f"{obj.name}: no pre-grasp candidate gives a clean nominal approach")
    opening, retreat, direction, q0, clearance, result = chosen

    log("[3/3] holding the goal grasp for 1 s")
    checks = hold_check(obj, q_goal, mass_scale=mass_scale)
    checks["hold_mass_scale"] = mass_scale
    checks.update(
        goal_cost=cost,
        pregrasp_opening=opening,
        pregrasp_retreat_m=retreat,
        pregrasp_direction=direction,
        pregrasp_clearance_m=float(clearance),
        nominal_approach_steps=int(result["step"]),
    )
    return GraspLabel(obj.name, Grasp(q0[:6].copy(), q0[6:].copy()), goal, goal_palm, checks)
