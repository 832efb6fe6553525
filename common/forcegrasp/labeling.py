"""Grasp labelling: find the goal functional grasp by optimisation, derive the pre-grasp by search.

Goal grasp Gg: nonlinear least squares (``mujoco.minimize.least_squares``) over the 30 joint
values, with the object at its nominal pose, from the start pose of the object file's
``grasp_hint``. Residuals, each a signed distance from ``mj_geomDistance`` or a position after
``mj_kinematics``:
- the functional finger's distal phalanx touches the functional part (gap -> -1 mm: the servo then presses);
- each finger of ``contacts`` rests on its parts, each of ``support_fingers`` anywhere on the
  object (gap -> 0), and the palm too where the hint asks for a power grasp (``palm_contact``);
- each fingertip or phalanx of ``targets`` reaches its point (which face it rests on);
- no hand geom penetrates the object or the table (penalty on depth beyond 1.2 mm);
- a small pull towards the start pose keeps the posture natural.
Of a few perturbed starts the lowest-residual solution that *holds* (``label_checks``) is kept.

Pre-grasp G0: candidates open the fingers part-way from Jg and back the palm off by 3-9 cm along
one of ``RETREAT_DIRECTIONS``; the first candidate with no contact anywhere in the jitter square
and the palm about 2 cm or more from the object, whose straight J = h(Jg - J0) + J0 sweep, played
by the scripted controller at the nominal placement, succeeds in the task's own terms is kept.
See ``docs/grasps.md``.
"""

from __future__ import annotations

import dataclasses
import io
from dataclasses import dataclass

import mujoco
import numpy as np
from mujoco import minimize

from forcegrasp.label_checks import place
from forcegrasp.labels import Grasp, GraspLabel
from forcegrasp.objects import ObjectSpec
from forcegrasp.scene import (
    ALL_JOINTS,
    HAND_JOINTS,
    SceneIndex,
    build_model,
    part_geoms,
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
    holds: list[tuple[int, list[int]]]  # (fingertip geom, the object geoms it may rest on)
    targets: list[tuple[str, int, np.ndarray]]  # ("site" or "geom", id, a point in the world it should reach)
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
        for tip, parts in self.holds:
            res.append(self.w_contact * min(dist(tip, g) for g in parts))
        for kind, i, point in self.targets:
            res.extend(self.w_contact * ((d.site_xpos[i] if kind == "site" else d.geom_xpos[i]) - point))
        if self.palm_contact:
            res.append(self.w_contact * min(dist(self.palm_geom, g) for g in ix.object_geoms))
        for h in ix.hand_geoms:
            for o in (*ix.object_geoms, self.table_geom):
                # Bounding spheres apart: no penetration, no query (a mesh object has many convex parts).
                if o != self.table_geom and (np.linalg.norm(d.geom_xpos[h] - d.geom_xpos[o])
                                             > m.geom_rbound[h] + m.geom_rbound[o]):
                    res.append(0.0)
                    continue
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


def solve_goal(obj: ObjectSpec, m: mujoco.MjModel | None = None, seed: int = 0, restarts: int = 4, log=print,
               accept=None):
    """Best goal grasp over a few perturbed starts: (q (30,), residual cost, problem).

    ``accept(q) -> bool`` (e.g. "it holds"), when given, ranks first the solutions it accepts: a
    low residual only says the contacts are where the hint asked, not that they grip."""
    m = m if m is not None else build_model(obj)
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    hint = obj.grasp_hint
    problem = GoalProblem(
        m=m,
        d=d,
        ix=ix,
        functional_geom=ix.fingertip_geoms[hint.functional_finger],
        part_geoms=[g for p in obj.functional_part for g in part_geoms(m, obj, p)],
        holds=holding_contacts(obj, m, ix),
        targets=[(*_target_frame(m, f), np.asarray(p) + [0.0, 0.0, resting_height(m)]) for f, p in hint.targets.items()],
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
        if hint.two_stage:  # thread first: the holding contacts would pull the fingers round the opening
            threading = dataclasses.replace(problem, holds=[])
            x0, _ = minimize.least_squares(x0, threading.residual, bounds=(lo, hi), max_iter=80, verbose=0,
                                           output=io.StringIO())
        x, _ = minimize.least_squares(x0, problem.residual, bounds=(lo, hi), max_iter=80, verbose=0, output=io.StringIO())
        cost = float(np.sum(problem.residual_one(x)[: -len(x)] ** 2))
        ok = accept is None or bool(accept(x))
        log(f"  start {attempt + 1}/{restarts}: contact+penetration cost {cost:.3e}"
            + ("" if accept is None else f", {'accepted' if ok else 'rejected by the checks'}"))
        if best is None or (not ok, cost) < (not best[2], best[1]):
            best = (x, cost, ok)
        if ok and cost < 1e-4:
            break
    return best[0], best[1], problem


def _target_frame(m: mujoco.MjModel, key: str) -> tuple[str, int]:
    """``ff`` -> the fingertip site; ``ff.middle`` -> the middle phalanx's collision capsule."""
    finger, _, segment = key.partition(".")
    return ("geom", m.geom(f"C_{finger}{segment}").id) if segment else ("site", m.site(f"S_{finger}tip").id)


def holding_contacts(obj: ObjectSpec, m: mujoco.MjModel, ix: SceneIndex) -> list[tuple[int, list[int]]]:
    """The hint's holding contacts: ``contacts`` (finger -> named parts) and ``support_fingers``
    (anywhere on the object)."""
    out = {f: [g for p in parts for g in part_geoms(m, obj, p)] for f, parts in obj.grasp_hint.contacts.items()}
    for f in obj.grasp_hint.support_fingers:
        out.setdefault(f, list(ix.object_geoms))
    return [(ix.fingertip_geoms[f], parts) for f, parts in out.items()]


def _table_geom(m: mujoco.MjModel) -> int:
    table = m.body("table").id
    return next(g for g in range(m.ngeom) if m.geom_bodyid[g] == table and m.geom_contype[g])


def hand_object_clearance(m, d, ix: SceneIndex) -> float:
    """Smallest signed distance between any hand geom and the object (negative = penetration)."""
    return min(mujoco.mj_geomDistance(m, d, h, o, 0.1, None) for h in ix.hand_geoms for o in ix.object_geoms)


#: Pre-grasp retreat directions, built from the goal pose: along the palm normal, back along the
#: forearm, upwards, towards the side the hand comes from (-y), and mixes. An object file's ``grasp_hint.approach`` says which to try first.
RETREAT_DIRECTIONS = ("palm normal", "back", "up", "back+up", "normal+up", "normal+back", "-y", "-y+up")
RETREATS_M = (0.03, 0.04, 0.05, 0.06, 0.07, 0.08, 0.09, 0.10)
KEEP_SHARE = 0.0  # how much of the opening a kept finger takes
OPENINGS = (0.5, 0.8, 1.0)  # fraction of the goal's finger flexion taken away at G0 (1: straight)


def pregrasp_candidates(m: mujoco.MjModel, q_goal: np.ndarray, first: tuple[str, ...] = (), keep: tuple[str, ...] = ()):
    """Yield (opening fraction, retreat distance, direction name, q0), nearest candidates first,
    the ``first`` directions ahead of the others at each distance; the fingers in ``keep`` open half
    as much (a finger that slides into an opening keeps most of its shape).

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
    toward_hand = np.array([0.0, -1.0, 0.0])  # the side the hand comes from (world -y): out along a handle's opening
    vectors = {"palm normal": -normal, "back": back, "up": up, "back+up": back + up, "normal+up": -normal + up,
               "normal+back": -normal + back, "-y": toward_hand, "-y+up": toward_hand + up}
    unknown = [a for a in first if a not in vectors]
    if unknown:
        raise ValueError(f"grasp_hint.approach names unknown directions {unknown}; known: {list(vectors)}")
    order = [*first, *(n for n in RETREAT_DIRECTIONS if n not in first)]
    flex = np.array([ALL_JOINTS.index(j) for j in FLEXION_JOINTS])
    # A kept finger opens half as much: straight enough to slide into its opening, curled enough to go on.
    share = np.array([KEEP_SHARE if j[:2].lower() in keep else 1.0 for j in FLEXION_JOINTS])
    S = slide_axes(m)
    for retreat in RETREATS_M:
        for name in order:
            direction = vectors[name] / np.linalg.norm(vectors[name])
            for opening in OPENINGS:
                q0 = q_goal.copy()
                q0[flex] = q_goal[flex] * (1.0 - opening * share)
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
    place(m, d, ix, q_goal)
    mujoco.mj_kinematics(m, d)
    return d.site_xpos[ix.palm_site] - d.xpos[ix.object_body]


def label_object(obj: ObjectSpec, mass_scale: float = 5.0, seed: int = 0, jitter: float = 0.02, log=print) -> GraspLabel:
    """Goal by optimisation, pre-grasp by search, checks recorded in the label (``label_checks``)."""
    from forcegrasp.env import FunctionalGraspEnv
    from forcegrasp.label_checks import (
        PALM_CLEARANCE_M,
        hold_check,
        lift_check,
        pregrasp_clearance,
        pregrasp_palm_error,
    )
    from forcegrasp.scripted import run_episode

    m = build_model(obj)
    if obj.grasp_hint.grasp:
        log(f"grasp: {obj.grasp_hint.grasp}")
    log(f"[1/3] goal grasp for {obj.name}: least squares over 30 joints")
    def grips(q) -> bool:  # the functional finger on its part, and the hand alone carries the object
        return hold_check(obj, q, mass_scale=mass_scale)["functional_contact"] and lift_check(obj, q, 1.0)["holds"]

    q_goal, cost, _ = solve_goal(obj, m, seed=seed, log=log, accept=grips)
    goal = Grasp(base=q_goal[:6].copy(), hand=q_goal[6:].copy())
    goal_palm = goal_palm_of(m, q_goal)

    log(f"[2/3] pre-grasp: search over finger opening and palm retreat, clear over the +-{jitter * 100:.0f} cm square")
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    rest_z = resting_height(m)
    chosen = None
    for opening, retreat, direction, q0 in pregrasp_candidates(m, q_goal, obj.grasp_hint.approach,
                                                                   obj.grasp_hint.keep_shape):
        place(m, d, ix, q0, rest_z=rest_z)
        mujoco.mj_kinematics(m, d)
        what = f"  {direction:>11}, retreat {retreat * 100:.0f} cm, opening {opening:.1f}:"
        if hand_object_clearance(m, d, ix) < 0.005:
            continue  # touching, or nearly, at the nominal placement: not worth a closer look
        reach = pregrasp_palm_error(m, q0, goal_palm, jitter, rest_z)
        if not reach["within_palm_tolerance"]:
            continue  # some placement would start beyond the env's palm tolerance and fail at step 1
        square = pregrasp_clearance(obj, q0, jitter)
        if not square["clear"] or square["palm_distance_m"] < PALM_CLEARANCE_M * 0.9:
            log(f"{what} clearance {square['min_clearance_m'] * 1000:.1f} mm over the square, palm "
                f"{square['palm_distance_m'] * 1000:.0f} mm away: rejected")
            continue
        label = GraspLabel(obj.name, Grasp(q0[:6].copy(), q0[6:].copy()), goal, goal_palm)
        env = FunctionalGraspEnv(obj.name, mass_scale=mass_scale, label=label)
        result = run_episode(env, (0.0, 0.0), told=True)
        log(f"{what} clear over the square (>= {square['min_clearance_m'] * 1000:.1f} mm), palm "
            f"{square['palm_distance_m'] * 1000:.0f} mm away, nominal approach "
            f"{'succeeds' if result['success'] else 'fails (' + str(result['failure']) + ')'}")
        if result["success"]:
            chosen = (opening, retreat, direction, q0, square, result, reach)
            break
    if chosen is None:
        raise RuntimeError(f"{obj.name}: no pre-grasp candidate is clear over the jitter square with a clean approach")
    opening, retreat, direction, q0, square, result, reach = chosen

    log(f"[3/3] holding the goal grasp for 1 s: on the table at {mass_scale:g}x mass, in the air at 1x and {mass_scale:g}x")
    checks = hold_check(obj, q_goal, mass_scale=mass_scale)
    checks["hold_mass_scale"] = mass_scale
    lift = lift_check(obj, q_goal, 1.0)
    heavy = lift_check(obj, q_goal, mass_scale)
    checks.update(
        holds=lift["holds"],
        hold_fingers=lift["fingers_in_contact"],
        hold_moved_in_palm_m=lift["object_moved_in_palm_m"],
        holds_heavy=heavy["holds"],
        hold_heavy_moved_in_palm_m=heavy["object_moved_in_palm_m"],
        goal_cost=cost,
        pregrasp_opening=opening,
        pregrasp_retreat_m=retreat,
        pregrasp_direction=direction,
        pregrasp_clearance_m=square["min_clearance_m"],
        pregrasp_palm_distance_m=square["palm_distance_m"],
        pregrasp_clear_over_square=square["clear"],
        pregrasp_worst_palm_error_m=reach["worst_palm_error_m"],
        pregrasp_within_palm_tolerance=reach["within_palm_tolerance"],
        nominal_approach_steps=int(result["step"]),
    )
    return GraspLabel(obj.name, Grasp(q0[:6].copy(), q0[6:].copy()), goal, goal_palm, checks)
