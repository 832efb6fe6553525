"""The simulated scene: the ADROIT hand from gymnasium-robotics, edited as the paper did, plus
one object built from primitives.

Edits to the stock model (``adroit_relocate.xml``), and why:
- all 44 fixed tendons removed: they couple finger joints and soften the force signal;
- every one of the 30 actuators rewritten as a position servo (gain kp, bias -kp, -kv) with a
  raised force limit, so targets are tracked and joint torques carry contact information;
- gravity compensation on the hand bodies and the implicit-fast integrator, so high gains and
  damping stay stable at the stock 2 ms timestep;
- the base rotation ranges widened (the stock +-0.75 rad cannot turn the palm sideways) and
  the base allowed to sink (stock ARTy only rises);
- the stock sphere, mocap tracker and target site removed; the object is a free body.

A mesh object (`forcegrasp.objects.MeshSpec`) is one visual mesh geom (no contacts, group 2) that
carries the mass, MuJoCo computing its inertia from the closed mesh at uniform density, plus one
colliding geom per convex part (group 3, no mass), plus, per region, the convex parts clipped to it
(no contacts, no mass, group 5): the geoms that `part_geoms` returns for a region's name.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from forcegrasp.objects import MESH_PART, ObjectFileError, ObjectSpec

BASE_JOINTS = ("ARTx", "ARTy", "ARTz", "ARRx", "ARRy", "ARRz")
HAND_JOINTS = (
    "WRJ1", "WRJ0",
    "FFJ3", "FFJ2", "FFJ1", "FFJ0",
    "MFJ3", "MFJ2", "MFJ1", "MFJ0",
    "RFJ3", "RFJ2", "RFJ1", "RFJ0",
    "LFJ4", "LFJ3", "LFJ2", "LFJ1", "LFJ0",
    "THJ4", "THJ3", "THJ2", "THJ1", "THJ0",
)  # fmt: skip
ALL_JOINTS = BASE_JOINTS + HAND_JOINTS
FINGERTIP_GEOMS = {f: f"C_{f}distal" for f in ("ff", "mf", "rf", "lf", "th")}
PALM_SITE = "S_grasp"
OBJECT_BODY = "object"
TABLE_TOP_Z = 0.0


@dataclass(frozen=True)
class ServoGains:
    """Position-servo gains: kp (N/m or N·m/rad), kv and the force limit, per joint group."""

    base_translation: tuple[float, float, float] = (5000.0, 300.0, 400.0)
    base_rotation: tuple[float, float, float] = (500.0, 40.0, 150.0)
    wrist: tuple[float, float, float] = (50.0, 2.0, 20.0)
    finger: tuple[float, float, float] = (60.0, 1.0, 20.0)


BASE_ROTATION_RANGE = 1.6  # rad, each of ARRx/ARRy/ARRz
BASE_HEIGHT_RANGE = (-0.2, 0.2)  # m, ARTy (stock 0..0.2 cannot lower the palm beside a mug)


def adroit_xml_path() -> Path:
    """The ADROIT relocate scene shipped inside the installed gymnasium-robotics package."""
    import importlib.util

    found = importlib.util.find_spec("gymnasium_robotics")  # located, not imported: import is slow and noisy
    if found is None or found.origin is None:
        raise FileNotFoundError("gymnasium-robotics is not installed; it provides the ADROIT hand model")
    path = Path(found.origin).parent / "envs" / "assets" / "adroit_hand" / "adroit_relocate.xml"
    if not path.is_file():
        raise FileNotFoundError(f"ADROIT model not found at {path}: is gymnasium-robotics installed?")
    return path


def _hand_bodies(spec: mujoco.MjSpec) -> list:
    forearm = spec.body("forearm")
    return [forearm, *forearm.find_all(mujoco.mjtObj.mjOBJ_BODY)]


def _edit_hand(spec: mujoco.MjSpec, gains: ServoGains) -> None:
    for tendon in list(spec.tendons):
        spec.delete(tendon)
    for name in ("Object", "vive_tracker"):
        body = spec.body(name)
        if body is not None:
            spec.delete(body)
    target = spec.site("target")
    if target is not None:
        spec.delete(target)
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    for body in _hand_bodies(spec):
        body.gravcomp = 1.0
    for name in BASE_JOINTS[3:]:
        spec.joint(name).range = [-BASE_ROTATION_RANGE, BASE_ROTATION_RANGE]
    spec.joint("ARTy").range = list(BASE_HEIGHT_RANGE)
    spec.joint("THJ4").range = [-1.047, 1.047]

    for actuator in spec.actuators:
        joint_name = actuator.target
        joint = spec.joint(joint_name)
        if joint_name in BASE_JOINTS[:3]:
            kp, kv, fmax = gains.base_translation
        elif joint_name in BASE_JOINTS[3:]:
            kp, kv, fmax = gains.base_rotation
        elif joint_name.startswith("WR"):
            kp, kv, fmax = gains.wrist
        else:
            kp, kv, fmax = gains.finger
        actuator.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        actuator.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        actuator.gainprm[:3] = [kp, 0.0, 0.0]
        actuator.biasprm[:3] = [0.0, -kp, -kv]
        actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.ctrlrange = list(joint.range)
        actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.forcerange = [-fmax, fmax]


_GEOM_TYPE = {
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
    "ellipsoid": mujoco.mjtGeom.mjGEOM_ELLIPSOID,
}


def object_geom_name(obj: ObjectSpec, geom: str) -> str:
    return f"{obj.name}/{geom}"


#: geom groups of a mesh object's geoms (MuJoCo shows groups 0-2 by default)
VISUAL_GROUP, COLLISION_GROUP, REGION_GROUP = 2, 3, 5  # the hand: visual 1, collision 4
REGION_RGBA = (1.0, 0.45, 0.0, 1.0)


def part_geom_prefix(obj: ObjectSpec, part: str) -> str | None:
    """Geom-name prefix of a mesh part (``mesh``: the convex parts; a region: its pieces), or None
    for a primitive geom (named `object_geom_name`)."""
    if obj.mesh is not None and part == MESH_PART:
        return f"{obj.name}/{MESH_PART}#"
    if part in obj.regions:
        return f"{obj.name}/{part}#"
    return None


def part_geoms(m: mujoco.MjModel, obj: ObjectSpec, part: str) -> list[int]:
    """Geom ids of a named part: a primitive geom, a mesh region's pieces, or (``mesh``) the convex parts."""
    prefix = part_geom_prefix(obj, part)
    if prefix is None:
        return [m.geom(object_geom_name(obj, part)).id]
    return [g for g in range(m.ngeom) if m.geom(g).name.startswith(prefix)]


def _add_object(spec: mujoco.MjSpec, obj: ObjectSpec, mass_scale: float) -> None:
    body = spec.worldbody.add_body(name=OBJECT_BODY, pos=[0.0, 0.0, TABLE_TOP_Z])
    body.add_freejoint(name="object_free")
    body.add_site(name="object_origin", pos=[0, 0, 0], size=[0.004, 0, 0], rgba=[1, 0, 0, 0.5])
    visual = _mesh_visual(obj) if obj.mesh is not None else None
    mesh_volume = 0.0 if visual is None else visual[2]
    total_volume = sum(g.volume() for g in obj.geoms) + mesh_volume
    for g in obj.geoms:
        _add_geom(body, obj, g, mass_scale, total_volume)
    if visual is not None:
        _add_mesh(spec, body, obj, visual, obj.mass * mass_scale * mesh_volume / total_volume)


def _mesh_visual(obj: ObjectSpec) -> tuple[np.ndarray, np.ndarray, float]:
    from forcegrasp.meshes import mesh_volume, read_obj_cached

    blocks = read_obj_cached(obj.mesh.visual)
    if not blocks:
        raise ObjectFileError(f"{obj.name}: {obj.mesh.visual} has no faces")
    offsets = np.cumsum([0] + [len(V) for _, V, _ in blocks])
    V = np.vstack([V for _, V, _ in blocks])
    F = np.vstack([F + o for (_, _, F), o in zip(blocks, offsets)])
    volume = mesh_volume(V, F)
    if volume <= 0:
        raise ObjectFileError(f"{obj.name}: {obj.mesh.visual} encloses no volume ({volume:.3g} m^3): import it again")
    return V, F, volume


def _mesh_geom(spec: mujoco.MjSpec, body, name: str, V: np.ndarray, F: np.ndarray, inertia) -> object:
    mesh = spec.add_mesh(name=name)
    mesh.scale = [1.0, 1.0, 1.0]  # the ADROIT file's mesh default scales its mm meshes by 0.001: ours are in m
    mesh.refpos, mesh.refquat = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    mesh.uservert = np.asarray(V, float).ravel().tolist()
    mesh.userface = np.asarray(F, int).ravel().tolist()
    mesh.inertia = inertia
    geom = body.add_geom()
    geom.name = name
    geom.type = mujoco.mjtGeom.mjGEOM_MESH
    geom.meshname = name
    return geom


def _add_mesh(spec: mujoco.MjSpec, body, obj: ObjectSpec, visual, mass: float) -> None:
    from forcegrasp.meshes import convex_triangles, read_obj_cached, region_pieces

    V, F, _ = visual
    geom = _mesh_geom(spec, body, object_geom_name(obj, MESH_PART), V, F, mujoco.mjtMeshInertia.mjMESH_INERTIA_EXACT)
    geom.mass = mass  # MuJoCo: inertia from the closed mesh at the uniform density this mass gives
    geom.contype = geom.conaffinity = 0
    geom.group = VISUAL_GROUP
    geom.rgba = list(obj.mesh.rgba)
    parts = read_obj_cached(obj.mesh.parts)
    if not parts:
        raise ObjectFileError(f"{obj.name}: {obj.mesh.parts} has no convex parts: import it again")
    for k, (_, PV, PF) in enumerate(parts):
        geom = _mesh_geom(spec, body, f"{part_geom_prefix(obj, MESH_PART)}{k}", PV, PF,
                          mujoco.mjtMeshInertia.mjMESH_INERTIA_CONVEX)
        geom.mass = 0.0
        geom.friction = list(obj.friction)
        geom.contype = geom.conaffinity = 1
        geom.condim = 4
        geom.group = COLLISION_GROUP
        geom.rgba = list(obj.mesh.rgba[:3]) + [0.5]
    for name, region in obj.regions.items():
        pieces = region_pieces(obj.mesh.parts, region.kind, region.center, region.size)
        if not pieces:
            raise ObjectFileError(f"{obj.name}: field 'regions.{name}' touches none of the mesh's convex parts")
        for k, piece in enumerate(pieces):
            RV, RF = convex_triangles(piece)
            geom = _mesh_geom(spec, body, f"{part_geom_prefix(obj, name)}{k}", RV, RF,
                              mujoco.mjtMeshInertia.mjMESH_INERTIA_CONVEX)
            geom.mass = 0.0
            geom.contype = geom.conaffinity = 0
            geom.group = REGION_GROUP
            geom.rgba = list(REGION_RGBA)


def _add_geom(body, obj: ObjectSpec, g, mass_scale: float, total_volume: float) -> None:
    geom = body.add_geom()
    geom.name = object_geom_name(obj, g.name)
    geom.type = _GEOM_TYPE[g.type]
    geom.size = list(g.size) + [0.0] * (3 - len(g.size))
    geom.pos = list(g.pos)
    geom.alt.type = mujoco.mjtOrientation.mjORIENTATION_EULER
    geom.alt.euler = list(g.euler)
    geom.rgba = list(g.rgba)
    geom.mass = obj.mass * mass_scale * g.volume() / total_volume
    geom.friction = list(obj.friction)
    geom.contype = 1
    geom.conaffinity = 1
    geom.condim = 4


def build_spec(obj: ObjectSpec, mass_scale: float = 1.0, gains: ServoGains = ServoGains()) -> mujoco.MjSpec:
    """The edited ADROIT scene with ``obj`` at the origin of the table, ``mass_scale`` × its mass."""
    if not np.isfinite(mass_scale) or mass_scale <= 0:
        raise ValueError(f"mass_scale must be a positive number, got {mass_scale!r}")
    spec = mujoco.MjSpec.from_file(str(adroit_xml_path()))
    _edit_hand(spec, gains)
    _add_object(spec, obj, mass_scale)
    return spec


def build_model(obj: ObjectSpec, mass_scale: float = 1.0, gains: ServoGains = ServoGains()) -> mujoco.MjModel:
    return build_spec(obj, mass_scale, gains).compile()


@dataclass(frozen=True)
class SceneIndex:
    """Addresses into MjModel/MjData arrays, computed once so the env's hot path is indexing only."""

    base_qpos: np.ndarray
    hand_qpos: np.ndarray
    all_qpos: np.ndarray
    all_dof: np.ndarray
    base_act: np.ndarray
    hand_act: np.ndarray
    hand_range: np.ndarray  # (24, 2)
    all_range: np.ndarray  # (30, 2)
    object_qpos: int  # first of 7 free-joint qpos (pos, quat)
    object_dof: int
    object_body: int
    palm_site: int
    hand_geoms: np.ndarray
    object_geoms: np.ndarray
    fingertip_geoms: dict

    @classmethod
    def of(cls, m: mujoco.MjModel) -> "SceneIndex":
        jid = [m.joint(n).id for n in ALL_JOINTS]
        act = {m.actuator_trnid[a, 0]: a for a in range(m.nu)}
        obj_joint = m.joint("object_free").id
        obj_body = m.body(OBJECT_BODY).id
        forearm = m.body("forearm").id
        hand_bodies = {b for b in range(m.nbody) if _is_descendant(m, b, forearm)}
        return cls(
            base_qpos=m.jnt_qposadr[jid[:6]].copy(),
            hand_qpos=m.jnt_qposadr[jid[6:]].copy(),
            all_qpos=m.jnt_qposadr[jid].copy(),
            all_dof=m.jnt_dofadr[jid].copy(),
            base_act=np.array([act[j] for j in jid[:6]]),
            hand_act=np.array([act[j] for j in jid[6:]]),
            hand_range=m.jnt_range[jid[6:]].copy(),
            all_range=m.jnt_range[jid].copy(),
            object_qpos=int(m.jnt_qposadr[obj_joint]),
            object_dof=int(m.jnt_dofadr[obj_joint]),
            object_body=obj_body,
            palm_site=m.site(PALM_SITE).id,
            hand_geoms=np.array(
                [g for g in range(m.ngeom) if m.geom_bodyid[g] in hand_bodies and m.geom_contype[g]]
            ),
            # the geoms that collide: a mesh object's visual mesh and region pieces are for looks and queries
            object_geoms=np.array([g for g in range(m.ngeom) if m.geom_bodyid[g] == obj_body
                                   and (m.geom_contype[g] or m.geom_conaffinity[g])]),
            fingertip_geoms={f: m.geom(n).id for f, n in FINGERTIP_GEOMS.items()},
        )


def _is_descendant(m: mujoco.MjModel, body: int, ancestor: int) -> bool:
    while body > 0:
        if body == ancestor:
            return True
        body = m.body_parentid[body]
    return False


def slide_axes(m: mujoco.MjModel) -> np.ndarray:
    """3x3 matrix S whose columns are the world directions of ARTx, ARTy, ARTz.

    The slides come first in the base's joint chain, so a world translation t of the whole hand
    is the slide change S.T @ t (S is a rotation).
    """
    forearm = m.body("forearm").id
    quat = m.body_quat[forearm]
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, quat)
    return mat.reshape(3, 3)


def resting_height(m: mujoco.MjModel, seconds: float = 0.3) -> float:
    """Height at which the object rests on the table: soft contacts sink it ~1 mm below z=0.

    Starting episodes at the rest height keeps that settling out of the object-displacement
    reward and the success test. The hand is parked out of the way while the object settles.
    A mesh object's frame has its lowest vertex on z = 0 and its convex parts are cut to the mesh's
    bounding box (``forcegrasp object import``), so it settles the way primitives do.
    """
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    d.qpos[ix.base_qpos[1]] = m.jnt_range[m.joint("ARTy").id, 1]  # lift the hand clear
    d.ctrl[ix.base_act[1]] = d.qpos[ix.base_qpos[1]]
    d.qpos[ix.object_qpos + 3] = 1.0
    for _ in range(int(seconds / m.opt.timestep)):
        mujoco.mj_step(m, d)
    return float(d.qpos[ix.object_qpos + 2])


def block_view(array: np.ndarray, index: np.ndarray) -> np.ndarray:
    """A view of ``array[index]`` when the indices are one contiguous run (MuJoCo keeps a body's
    joints and a model's actuators in order); anything else is refused, since the copy that fancy
    indexing makes would silently stop tracking MjData."""
    index = np.asarray(index)
    if index.size and np.array_equal(index, np.arange(index[0], index[0] + index.size)):
        return array[index[0] : index[0] + index.size]
    raise ValueError("expected contiguous base and hand blocks in qpos and ctrl")
