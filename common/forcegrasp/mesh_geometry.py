"""Meshes as geometry: load, repair and measure a mesh file, decompose it into convex parts, check
the parts cover it, check the built object rests, and picture it. The pieces `forcegrasp object
import` (`forcegrasp.mesh_import`) is built from; each refuses bad input with a `MeshImportError`
that says why and what to do."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from forcegrasp.objects import MESH_SUFFIXES

SIZE_RANGE_M = (0.015, 0.6)  # largest extent of an object a hand can grasp
REST_TILT_LIMIT_DEG = 5.0  # the settled object may lean this much


class MeshImportError(ValueError):
    """A mesh file cannot become an object; the message says why and what to do."""


def _euler_matrix(euler_deg) -> np.ndarray:
    """Rotation about x, then y, then z (fixed axes), degrees."""
    rx, ry, rz = np.radians(np.asarray(euler_deg, float))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


# ------------------------------------------------------------------------------------ geometry
def load_mesh(path: Path):
    """The file's triangles as one trimesh (degenerate and duplicate triangles dropped), refused
    when it is not a mesh file, is empty or spans no volume."""
    import trimesh

    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise MeshImportError(f"{path}: not a mesh file: expected OBJ or STL ({', '.join(MESH_SUFFIXES)}), "
                              f"got {path.suffix or 'no suffix'!r}")
    if not path.is_file():
        raise MeshImportError(f"{path}: no such file")
    try:
        loaded = trimesh.load(str(path), force="mesh", process=True)
    except Exception as exc:  # noqa: BLE001  (any parser failure means: not a readable mesh)
        raise MeshImportError(f"{path}: not a readable {path.suffix[1:].upper()} mesh "
                              f"({type(exc).__name__}: {exc})") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshImportError(f"{path}: empty mesh: no triangles in the file (is it a mesh at all?)")
    mesh = loaded
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    extents = mesh.extents if len(mesh.faces) else np.zeros(3)
    if len(mesh.faces) < 4 or extents.max() <= 0 or extents.min() <= 1e-6 * extents.max() or mesh.area <= 0:
        raise MeshImportError(f"{path}: degenerate mesh: its {len(mesh.faces)} non-degenerate triangles span no "
                              f"volume (extents {', '.join(f'{e:.3g}' for e in extents)}): flat, a line or a point")
    return mesh


def obj_groups(path: Path) -> dict:
    """Vertices (source frame) of each group and object of an OBJ file, by name."""
    import trimesh

    out = {}
    if Path(path).suffix.lower() != ".obj":
        return out
    for kw in ({"split_objects": True}, {"split_groups": True}):
        try:
            scene = trimesh.load(str(path), force="scene", group_material=False, process=False, **kw)
        except Exception:  # noqa: BLE001
            continue
        for name, geom in scene.geometry.items():
            if len(getattr(geom, "vertices", ())):
                out.setdefault(str(name), np.asarray(geom.vertices, float))
    return out


def close_mesh(mesh) -> list[str]:
    """Repair in place until watertight with outward normals; the repairs made, in words.
    Refuses a mesh that stays open."""
    import trimesh

    done = []
    if not mesh.is_watertight:
        before = len(mesh.vertices)
        mesh.merge_vertices()
        if len(mesh.vertices) < before:
            done.append(f"merged {before - len(mesh.vertices)} duplicate vertices")
    if not mesh.is_watertight:
        open_edges = _open_edges(mesh)
        trimesh.repair.fill_holes(mesh, use_fan=True)
        if _open_edges(mesh) < open_edges:
            done.append(f"filled holes ({open_edges} open edges)")
    if not mesh.is_watertight:
        raise MeshImportError(f"mesh is not watertight: {_open_edges(mesh)} open or non-manifold edges remain after "
                              "trying to repair it (merge vertices, fill holes): its mass and inertia need a closed "
                              "surface; close it in a mesh editor")
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
        done.append("made the triangle winding consistent")
    if mesh.volume < 0:
        mesh.invert()
        done.append("turned the normals outwards")
    if not mesh.is_volume or mesh.volume <= 0:
        raise MeshImportError("mesh is closed but encloses no consistent volume (self-overlapping or inside out); "
                              "fix it in a mesh editor")
    return done


def _open_edges(mesh) -> int:
    from trimesh.grouping import group_rows

    edges = mesh.edges_sorted
    return len(edges) - 2 * len(group_rows(edges, require_count=2))


def check_size(extents: np.ndarray, scale: float, source: str) -> None:
    largest = float(np.max(extents))
    lo, hi = SIZE_RANGE_M
    if lo <= largest <= hi:
        return
    suggest = scale * 10.0 ** round(math.log10(0.1 / largest))
    how = "too big" if largest > hi else "too small"
    factor = largest / hi if largest > hi else lo / largest
    raise MeshImportError(
        f"{source}: the object would be {largest:.4g} m across (largest extent at --scale {scale:g}), {factor:.0f}x "
        f"{how} for a hand, which grasps objects of {lo * 100:g}-{hi * 100:g} cm: wrong units? try --scale {suggest:g}")


def inside_mesh(V: np.ndarray, F: np.ndarray, points: np.ndarray, chunk: int = 512) -> np.ndarray:
    """Which points lie inside a closed triangle mesh (generalised winding number > 1/2)."""
    tri = V[F]
    out = np.empty(len(points), bool)
    for s in range(0, len(points), chunk):
        p = points[s:s + chunk]
        a, b, c = (tri[None, :, k, :] - p[:, None, :] for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        det = np.einsum("ijk,ijk->ij", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ijk,ijk->ij", a, b) * lc + np.einsum("ijk,ijk->ij", b, c) * la \
            + np.einsum("ijk,ijk->ij", c, a) * lb
        w = np.arctan2(det, den).sum(axis=1) / (2 * np.pi)
        out[s:s + chunk] = w > 0.5
    return out


def inside_convex(parts: list[np.ndarray], points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Which points lie inside any of the convex hulls of ``parts`` (vertex arrays)."""
    from scipy.spatial import ConvexHull

    out = np.zeros(len(points), bool)
    for V in parts:
        eq = ConvexHull(V).equations
        out |= np.all(points @ eq[:, :3].T + eq[:, 3] <= tol, axis=1)
    return out


def coverage(V: np.ndarray, F: np.ndarray, parts: list[np.ndarray], samples: int = 20000, seed: int = 0) -> dict:
    """Monte Carlo over the bounding box of mesh and parts: the share of the mesh's volume inside
    the parts (``covered``), the parts' union volume relative to the mesh's (``union_over_mesh``)."""
    allv = np.vstack([V, *parts])
    lo, hi = allv.min(axis=0), allv.max(axis=0)
    pts = np.random.default_rng(seed).uniform(lo, hi, (samples, 3))
    in_mesh, in_parts = inside_mesh(V, F, pts), inside_convex(parts, pts)
    return {"covered": float((in_mesh & in_parts).sum() / max(1, in_mesh.sum())),
            "union_over_mesh": float(in_parts.sum() / max(1, in_mesh.sum())), "samples": samples}


def decompose(V: np.ndarray, F: np.ndarray, threshold: float = 0.05, max_parts: int = -1, seed: int = 0,
              **coacd_kw) -> tuple[list[tuple[np.ndarray, np.ndarray]], float, float]:
    """CoACD's convex parts, the wall seconds and the CPU seconds (all threads) taken: each part the
    convex hull of CoACD's (vertices, outward triangles) cut to the mesh's bounding box (CoACD's hulls stand up to ~1 mm proud of the
    surface; at the bottom that would lift the object off the table)."""
    import coacd

    from forcegrasp.meshes import clip_convex, convex_triangles, region_halfspaces

    V = np.asarray(V, float)
    lo, hi = V.min(axis=0), V.max(axis=0)
    bounds = region_halfspaces("box", (lo + hi) / 2, (hi - lo) / 2)

    coacd.set_log_level("error")
    t0, cpu0 = time.perf_counter(), time.process_time()
    raw = coacd.run_coacd(coacd.Mesh(np.asarray(V, float), np.asarray(F, np.int32)), threshold=threshold,
                          max_convex_hull=max_parts, seed=seed, **coacd_kw)
    seconds = time.perf_counter() - t0
    cpu_seconds = time.process_time() - cpu0  # the wall time on a busy machine says little
    parts = []
    for pv, _ in raw:
        inside = clip_convex(np.asarray(pv, float), *bounds)
        if inside is None:
            continue  # a flat sliver: no volume to collide with
        parts.append(convex_triangles(inside))
    if not parts:
        raise MeshImportError("the convex decomposition returned no parts with volume")
    return parts, seconds, cpu_seconds


def surface_points(mesh, count: int = 20000) -> np.ndarray:
    """Vertices, triangle centres and ``count`` area-weighted samples of the surface (seeded)."""
    import trimesh

    samples, _ = trimesh.sample.sample_surface(mesh, count, seed=0)
    return np.vstack([mesh.vertices, mesh.triangles_center, samples])


# ------------------------------------------------------------------------------------ the built object


def rest_check(obj, seconds: float = 1.0) -> dict:
    """Settle the object on the table (hand parked above) for ``seconds``; refuse a pose that tips."""
    import mujoco

    from forcegrasp.scene import SceneIndex, build_model

    try:
        m = build_model(obj)
    except (ValueError, RuntimeError) as exc:  # MuJoCo refuses a mesh: report it as the import's error
        raise MeshImportError(f"MuJoCo cannot build the scene: {exc}") from exc
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    d.qpos[ix.base_qpos[1]] = m.jnt_range[m.joint("ARTy").id, 1]
    d.ctrl[ix.base_act[1]] = d.qpos[ix.base_qpos[1]]
    d.qpos[ix.object_qpos + 3] = 1.0
    for _ in range(int(seconds / m.opt.timestep)):
        mujoco.mj_step(m, d)
    z_axis = d.xmat[ix.object_body].reshape(3, 3)[:, 2]
    tilt = float(np.degrees(np.arccos(np.clip(z_axis[2], -1.0, 1.0))))
    slide = float(np.linalg.norm(d.xpos[ix.object_body][:2]))
    if tilt > REST_TILT_LIMIT_DEG or slide > 0.01:
        raise MeshImportError(f"the object does not rest in this pose: on the table it tips {tilt:.1f} deg and slides "
                              f"{slide * 1000:.0f} mm in {seconds:g} s; turn it with --euler so it stands on a "
                              "flat side")
    return {"tilt_deg": tilt, "z_m": float(d.qpos[ix.object_qpos + 2]), "mass_kg": float(m.body_mass[ix.object_body]),
            "inertia_principal": [float(v) for v in m.body_inertia[ix.object_body]]}


def object_picture(obj, height: int = 300, width: int = 400) -> np.ndarray:
    """Three views side by side: the object's view with the visual mesh translucent and the
    functional part's pieces in orange; the same with the convex parts instead; from above."""
    import mujoco

    from forcegrasp.render import look_at, make_renderer, object_camera
    from forcegrasp.scene import COLLISION_GROUP, REGION_GROUP, VISUAL_GROUP, SceneIndex, build_model, part_geoms

    m = build_model(obj)
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    d.qpos[ix.base_qpos[1]] = m.jnt_range[m.joint("ARTy").id, 1]  # the hand out of the way, above
    d.qpos[ix.object_qpos + 3] = 1.0
    mujoco.mj_forward(m, d)
    functional = {g for p in obj.functional_part for g in part_geoms(m, obj, p)}
    rng = np.random.default_rng(0)
    for g in range(m.ngeom):
        if m.geom_bodyid[g] != ix.object_body:
            continue
        if m.geom_group[g] == VISUAL_GROUP:
            m.geom_rgba[g, 3] = 0.35
        elif m.geom_group[g] == COLLISION_GROUP:
            m.geom_rgba[g] = [*rng.uniform(0.2, 0.95, 3), 1.0]
        elif m.geom_group[g] == REGION_GROUP and g not in functional:
            m.geom_rgba[g] = [0.2, 0.5, 1.0, 1.0]  # the hint's other regions in blue
    renderer = make_renderer(m, height, width)
    images = []
    cam = object_camera(obj.view, d.xpos[ix.object_body])
    top = look_at(d.xpos[ix.object_body] + np.asarray(obj.view.lookat), obj.view.distance, 270.0, -80.0)
    for camera, shown in ((cam, (VISUAL_GROUP, REGION_GROUP)), (cam, (COLLISION_GROUP,)),
                          (top, (VISUAL_GROUP, REGION_GROUP))):
        opt = mujoco.MjvOption()
        for grp in (VISUAL_GROUP, COLLISION_GROUP, REGION_GROUP):
            opt.geomgroup[grp] = grp in shown
        renderer.update_scene(d, camera, opt)
        images.append(renderer.render())
    renderer.close()
    return np.concatenate(images, axis=1)
