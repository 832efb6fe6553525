"""Mesh objects at run time: reading the files ``forcegrasp object import`` wrote, and the convex
pieces of a functional region.

Only numpy and scipy here (no trimesh, no CoACD): building a scene never re-decomposes and never
repairs; it reads two small OBJ files (``visual.obj``: the repaired mesh, ``parts.obj``: its convex
parts, one ``o`` block each), both already in the object's frame and in metres.

A *region* (a box or a sphere in object coordinates, see `forcegrasp.objects.Region`) names part
of the mesh's surface: the functional part, or a place a finger should rest (``grasp_hint.contacts``).
The scene realises a region as the convex parts clipped to it: each piece is convex (a convex
part cut by the region's half-spaces), lies inside the object, and its outer faces are the object's
surface inside the region. Those pieces are non-colliding geoms (no contacts, no mass); distance
queries (``mj_geomDistance``) still see them, so "the finger touches the functional part" means, as
for primitives, "the finger is within 1 mm of one of the part's geoms", here: of the object's
surface inside the region. A sphere is clipped as the polytope of 42 planes tangent to it (its
corners at most 7.1 % of the radius farther out than the sphere).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

#: unit directions of the 42 tangent planes that stand in for a sphere region
_ICO_PHI = (1 + 5 ** 0.5) / 2


def _sphere_directions() -> np.ndarray:
    p = _ICO_PHI
    v = np.array([(-1, p, 0), (1, p, 0), (-1, -p, 0), (1, -p, 0), (0, -1, p), (0, 1, p), (0, -1, -p), (0, 1, -p),
                  (p, 0, -1), (p, 0, 1), (-p, 0, -1), (-p, 0, 1)], float)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    d = np.linalg.norm(v[:, None] - v[None], axis=2)
    edge = d[d > 1e-9].min()
    i, j = np.nonzero(np.triu(np.abs(d - edge) < 1e-6))
    mid = v[i] + v[j]
    mid /= np.linalg.norm(mid, axis=1, keepdims=True)
    return np.vstack([v, mid])  # 12 vertices + 30 edge midpoints


SPHERE_DIRECTIONS = _sphere_directions()


# ----------------------------------------------------------------------------------------- OBJ files
def read_obj(path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``[(object name, vertices (n, 3), triangles (m, 3))]`` of an OBJ file, one entry per ``o``
    (or ``g``) block that has faces; polygons are fanned into triangles, texture and normal
    indices ignored, negative (relative) indices resolved. Vertices are shared by the whole file,
    so each block keeps only the ones it uses."""
    verts, blocks, name, faces = [], [], "", []

    def close():
        if faces:
            blocks.append((name, faces.copy()))
        faces.clear()

    for line in Path(path).read_text(errors="replace").splitlines():
        head, _, rest = line.strip().partition(" ")
        if head == "v":
            verts.append([float(x) for x in rest.split()[:3]])
        elif head in ("o", "g"):
            close()
            name = rest.strip()
        elif head == "f":
            idx = []
            for token in rest.split():
                i = int(token.split("/")[0])
                idx.append(i - 1 if i > 0 else len(verts) + i)
            faces.extend((idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1))
    close()
    V = np.asarray(verts, float).reshape(-1, 3)
    out = []
    for block_name, tri in blocks:
        tri = np.asarray(tri, int)
        used, inverse = np.unique(tri, return_inverse=True)
        out.append((block_name, V[used], inverse.reshape(-1, 3)))
    return out


def write_obj(path, blocks, header: str = "") -> None:
    """Write ``[(name, vertices, triangles)]`` as one OBJ file (an ``o`` block each, 1-based indices)."""
    lines = [f"# {h}" for h in header.splitlines()]
    offset = 1
    for name, V, F in blocks:
        lines.append(f"o {name}")
        lines.extend(f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in np.asarray(V, float))
        lines.extend(f"f {a + offset} {b + offset} {c + offset}" for a, b, c in np.asarray(F, int))
        offset += len(V)
    Path(path).write_text("\n".join(lines) + "\n")


def mesh_volume(V: np.ndarray, F: np.ndarray) -> float:
    """Signed volume of a closed triangle mesh (positive with outward-facing triangles)."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


@functools.lru_cache(maxsize=32)
def _read_cached(path: str, mtime_ns: int, size: int):
    return tuple((n, V.copy(), F.copy()) for n, V, F in read_obj(path))


def read_obj_cached(path) -> tuple:
    """`read_obj`, cached on the file's path, modification time and size (scenes are built often)."""
    st = Path(path).stat()
    return _read_cached(str(Path(path).resolve()), st.st_mtime_ns, st.st_size)


# ------------------------------------------------------------------------------------ convex pieces
def region_halfspaces(kind: str, center, size) -> tuple[np.ndarray, np.ndarray]:
    """``(A, b)`` with the region = {x : A x <= b}: a box's 6 faces (``size`` its half-sizes), or
    42 planes tangent to a sphere (``size`` [radius])."""
    c = np.asarray(center, float)
    if kind == "box":
        h = np.asarray(size, float)
        A = np.vstack([np.eye(3), -np.eye(3)])
        return A, np.concatenate([c + h, -(c - h)])
    A = SPHERE_DIRECTIONS
    return A, A @ c + float(size[0])


def region_contains(kind: str, center, size, points: np.ndarray, grow: float = 0.0) -> np.ndarray:
    """Which ``points`` lie inside the region (exactly: a box, or the sphere itself), grown by ``grow`` m."""
    p = np.asarray(points, float) - np.asarray(center, float)
    if kind == "box":
        return np.all(np.abs(p) <= np.asarray(size, float) + grow, axis=1)
    return np.linalg.norm(p, axis=1) <= float(size[0]) + grow


def _hull(points: np.ndarray):
    from scipy.spatial import ConvexHull, QhullError

    if len(points) < 4:
        return None
    try:
        return ConvexHull(points)
    except (QhullError, ValueError):  # flat or degenerate: no volume
        return None


def clip_convex(points: np.ndarray, A: np.ndarray, b: np.ndarray, min_volume: float = 1e-12) -> np.ndarray | None:
    """Vertices of conv(points) ∩ {A x <= b}, or None when that has (almost) no volume.

    Each cut keeps the vertices on the inner side and adds where the hull's edges cross the plane:
    the vertices of a convex polytope cut by a plane are among those."""
    pts = np.asarray(points, float)
    for a, beta in zip(A, b):
        hull = _hull(pts)
        if hull is None or hull.volume < min_volume:
            return None
        pts = pts[hull.vertices]
        s = pts @ a - beta
        if np.all(s <= 1e-12):
            continue
        if np.all(s >= -1e-12):
            return None
        index = {v: k for k, v in enumerate(hull.vertices)}
        edges = {tuple(sorted((index[u], index[w]))) for tri in hull.simplices for u, w in
                 ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))}
        e = np.array(sorted(edges))
        si, sj = s[e[:, 0]], s[e[:, 1]]
        crossing = (si < 0) != (sj < 0)
        i, j = e[crossing, 0], e[crossing, 1]
        t = (si[crossing] / (si[crossing] - sj[crossing]))[:, None]
        pts = np.vstack([pts[s <= 0], pts[i] + t * (pts[j] - pts[i])])
    hull = _hull(pts)
    if hull is None or hull.volume < min_volume:
        return None
    return pts[hull.vertices]


def convex_triangles(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices, outward triangles)`` of the convex hull of ``points``."""
    hull = _hull(np.asarray(points, float))
    if hull is None:
        raise ValueError("points span no volume")
    V = hull.points[hull.vertices]
    remap = {v: k for k, v in enumerate(hull.vertices)}
    F = np.array([[remap[i] for i in tri] for tri in hull.simplices])
    centre = V.mean(axis=0)
    for k, (tri, eq) in enumerate(zip(F, hull.equations)):  # qhull's simplices are unordered: face them out
        n = np.cross(V[tri[1]] - V[tri[0]], V[tri[2]] - V[tri[0]])
        if n @ eq[:3] < 0:
            F[k] = tri[[0, 2, 1]]
    return V, F


@functools.lru_cache(maxsize=64)
def _pieces_cached(path: str, mtime_ns: int, nbytes: int, kind: str, center: tuple, size: tuple) -> tuple:
    parts = _read_cached(path, mtime_ns, nbytes)
    A, b = region_halfspaces(kind, center, size)
    out = []
    for _, V, _ in parts:
        piece = clip_convex(V, A, b)
        if piece is not None:
            out.append(piece)
    return tuple(out)


def region_pieces(parts_path, kind: str, center, size) -> list[np.ndarray]:
    """The convex parts clipped to a region: a list of vertex arrays (each a convex polytope)."""
    st = Path(parts_path).stat()
    return list(_pieces_cached(str(Path(parts_path).resolve()), st.st_mtime_ns, st.st_size, kind,
                               tuple(map(float, center)), tuple(map(float, size))))
