"""Bring your own object: ``forcegrasp object import FILE --name NAME --mass KG``.

One import turns a mesh file (OBJ or STL) into an object of ``assets/objects/`` (the ``mesh`` entry
of `forcegrasp.objects`) with its files in ``assets/meshes/NAME/``:

1. load it (trimesh), drop degenerate triangles, refuse a file that is not a mesh, an empty mesh,
   or one whose triangles span no volume;
2. scale it (``--scale``: source units to m) and turn it (``--euler``, degrees); refuse it when its
   largest extent is outside 1.5 cm - 60 cm (a mesh in mm or in km is 100x too big or too small
   for a hand: the message proposes a ``--scale``);
3. close it: a mesh that is not watertight is repaired (merge vertices, fix winding and normals,
   fill the holes with fans); one that stays open is refused: its mass properties would be wrong;
4. rest it on the table: the lowest vertex on z = 0 and the centre of mass (``--center com``, the
   default), the bounding box's centre (``bbox``) or the source's own origin (``source``) over the
   object's origin; after the decomposition a 1 s settling simulation refuses a pose that tips over;
5. the functional part (``--part``): a box ``box:x,y,z,hx,hy,hz`` or a sphere ``sphere:x,y,z,r``
   (object frame, m: centre and half-sizes or radius), or ``group:NAME``, the bounding box (grown
   by 1 mm) of that group or object of the OBJ file; refused when it contains no point of the
   surface (more regions for the grasp hint's contacts: ``--region NAME=SPEC``);
6. mass properties at uniform density from ``--mass`` (kg): volume, centre of mass, inertia;
7. convex decomposition (CoACD, seed 0, ``--threshold`` its concavity threshold) into the parts
   the scene collides with, written once: training never decomposes again;
8. write ``visual.obj`` (the closed mesh, object frame, m), ``parts.obj`` (the convex parts), a copy
   of the source and the object file, all in a temporary folder inside the assets folder, checked
   by loading and building the scene from there, then moved into place by renames: an error at
   any step leaves nothing behind (an existing object is only replaced with ``--force``);
9. print what it measured and render the object with its functional part highlighted
   (``docs/objects/NAME.png``).

Without ``--hint FILE`` (a JSON file with a ``grasp_hint`` map, and optionally ``view`` and
``description``, or the bare hint map) the object gets a top-down start for ``forcegrasp label``:
the index finger on the functional part, middle finger and thumb in support, the palm facing down
5 cm above the object's top over the part's centre, fingers along +y. Edit it if the search fails.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from forcegrasp.mesh_geometry import (  # noqa: F401  (the geometry is part of this module's API)
    SIZE_RANGE_M, MeshImportError, _euler_matrix, check_size, close_mesh, coverage, decompose, inside_convex,
    inside_mesh, load_mesh, obj_groups, object_picture, rest_check, surface_points)
from forcegrasp.object_meshes import parse_region
from forcegrasp.objects import ObjectFileError, Region, load_object_file

GROUP_MARGIN_M = 0.001  # a group's box is its bounding box grown by this much
OUTPUTS = ("visual.obj", "parts.obj")


@dataclass
class ImportResult:
    name: str
    object_file: Path
    mesh_dir: Path
    extents_m: tuple
    watertight_source: bool
    repairs: list
    volume_m3: float
    mass_kg: float
    center_of_mass: tuple
    inertia: np.ndarray  # 3x3 about the centre of mass, object axes (kg m^2)
    parts: int
    decomposition_s: float
    decomposition_cpu_s: float
    coverage: dict
    region: dict
    rest: dict
    picture: Path | None = None
    notes: list = field(default_factory=list)

    def summary(self) -> str:
        ex = self.extents_m
        principal = np.linalg.eigvalsh(self.inertia)
        lines = [
            f"{self.name}: {ex[0] * 100:.1f} x {ex[1] * 100:.1f} x {ex[2] * 100:.1f} cm (x, y, z)",
            f"  watertight: {'yes' if self.watertight_source else 'no, repaired: ' + '; '.join(self.repairs)}",
            f"  volume {self.volume_m3 * 1e6:.1f} cm^3, mass {self.mass_kg:.3f} kg "
            f"(density {self.mass_kg / self.volume_m3:.0f} kg/m^3)",
            f"  centre of mass ({', '.join(f'{c * 100:.2f}' for c in self.center_of_mass)}) cm",
            "  inertia about the centre of mass (kg m^2): ["
            + "; ".join(" ".join(f"{v:.3e}" for v in row) for row in self.inertia) + "]",
            f"  principal moments {', '.join(f'{v:.3e}' for v in principal)} kg m^2",
            f"  convex parts: {self.parts} (CoACD, {self.decomposition_s:.1f} s, "
            f"{self.decomposition_cpu_s:.1f} s of CPU); they cover "
            f"{self.coverage['covered'] * 100:.1f} % of the mesh's volume, their union is "
            f"{self.coverage['union_over_mesh'] * 100:.1f} % of it",
            f"  functional part {self.region['name']}: {self.region['spec']} "
            f"({self.region['pieces']} convex pieces, {self.region['surface_share'] * 100:.1f} % of the surface)",
            f"  rests on the table at z {self.rest['z_m'] * 1000:+.2f} mm, leaning {self.rest['tilt_deg']:.2f} deg",
            f"wrote {self.object_file} and {self.mesh_dir}/",
        ]
        lines += [f"  note: {n}" for n in self.notes]
        if self.picture is not None:
            lines.append(f"wrote {self.picture} (functional part in orange; middle: the convex parts)")
        return "\n".join(lines)


# ------------------------------------------------------------------------------------ arguments
def parse_part_spec(text: str, what: str = "--part") -> tuple[str, list[float] | str]:
    """``box:x,y,z,hx,hy,hz``, ``sphere:x,y,z,r`` or ``group:NAME`` -> (kind, values or name)."""
    kind, sep, rest = str(text).partition(":")
    kind = kind.strip().lower()
    if not sep or kind not in ("box", "sphere", "group") or not rest.strip():
        raise MeshImportError(f"{what} {text!r}: expected box:x,y,z,hx,hy,hz or sphere:x,y,z,r (object frame, m) "
                              "or group:NAME (a group or object of the OBJ file)")
    if kind == "group":
        return kind, rest.strip()
    try:
        values = [float(v) for v in rest.split(",")]
    except ValueError:
        raise MeshImportError(f"{what} {text!r}: the values must be numbers") from None
    want = 6 if kind == "box" else 4
    if len(values) != want or not all(math.isfinite(v) for v in values) or min(values[3:]) <= 0:
        raise MeshImportError(f"{what} {text!r}: {kind} takes {want} numbers, the sizes positive")
    return kind, values


def default_hint(region: Region, top_z: float) -> dict:
    c = region.center
    return {
        "functional_finger": "ff",
        "support_fingers": ["mf", "th"],
        "grasp": "a default top-down start (forcegrasp object import): the index finger on the functional part",
        "rotation": [0.0, 0.0, 0.0],
        "palm_at": [round(c[0], 4), round(c[1] - 0.04, 4), round(top_z + 0.05, 4)],
    }


def _read_hint(path: Path) -> dict:
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise MeshImportError(f"--hint {path}: not readable JSON ({exc})") from exc
    if not isinstance(raw, dict):
        raise MeshImportError(f"--hint {path}: expected a JSON map")
    return raw if "grasp_hint" in raw else {"grasp_hint": raw}


def _region_of(kind: str, value, groups: dict, transform, what: str) -> Region:
    if kind == "group":
        if value not in groups:
            known = ", ".join(sorted(groups)) or "none"
            raise MeshImportError(f"{what} group:{value}: the file has no group or object {value!r} (it has: {known})")
        pts = transform(groups[value])
        lo, hi = pts.min(axis=0) - GROUP_MARGIN_M, pts.max(axis=0) + GROUP_MARGIN_M
        return Region("box", tuple((lo + hi) / 2), tuple((hi - lo) / 2), group=str(value))
    try:
        return parse_region({kind: value}, what)
    except ObjectFileError as exc:
        raise MeshImportError(str(exc)) from exc


def import_mesh(
    file,
    name: str,
    mass: float,
    *,
    scale: float = 1.0,
    part: str | None = None,
    part_name: str = "functional",
    regions: dict[str, str] | None = None,
    euler_deg=(0.0, 0.0, 0.0),
    center: str = "com",
    hint: Path | None = None,
    description: str = "",
    notice: Path | None = None,
    threshold: float = 0.05,
    max_parts: int = -1,
    coacd_options: dict | None = None,
    force: bool = False,
    assets_dir: Path | None = None,
    picture: Path | None | bool = True,
    rgba=(0.85, 0.85, 0.8, 1.0),
    log=print,
) -> ImportResult:
    """Import ``file`` as object ``name`` (see the module docstring); raises `MeshImportError`
    (nothing written) when it cannot."""
    from forcegrasp import ASSETS_DIR

    assets = Path(assets_dir) if assets_dir is not None else ASSETS_DIR
    file = Path(file)
    if not isinstance(name, str) or not name.isidentifier():
        raise MeshImportError(f"--name {name!r}: must be an identifier (letters, digits, _)")
    if isinstance(mass, bool) or not isinstance(mass, (int, float)) or not (math.isfinite(mass) and 0.001 <= mass <= 50):
        raise MeshImportError(f"--mass {mass!r}: must be a number of kg between 0.001 and 50")
    if not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale <= 0:
        raise MeshImportError(f"--scale {scale!r}: must be a positive number (source units to m)")
    if center not in ("com", "bbox", "source"):
        raise MeshImportError(f"--center {center!r}: one of com, bbox, source")
    if part is None:
        raise MeshImportError("--part is required: the functional part, box:x,y,z,hx,hy,hz, sphere:x,y,z,r "
                              "or group:NAME")
    if not part_name.isidentifier() or part_name == "mesh":
        raise MeshImportError(f"--part-name {part_name!r}: must be an identifier other than 'mesh'")
    object_file = assets / "objects" / f"{name}.json"
    mesh_dir = assets / "meshes" / name
    if object_file.exists() and not force:
        raise MeshImportError(f"object {name!r} exists ({object_file}); pass --force to replace it")
    specs = {part_name: parse_part_spec(part, "--part")}
    for rname, text in (regions or {}).items():
        if not str(rname).isidentifier() or rname in specs or rname == "mesh":
            raise MeshImportError(f"--region {rname}=...: the name must be a new identifier other than 'mesh'")
        specs[rname] = parse_part_spec(text, f"--region {rname}=")
    extra = _read_hint(hint) if hint is not None else {}

    # 1-3: load, scale and turn, size, close
    mesh = load_mesh(file)
    watertight = bool(mesh.is_watertight)
    rot = _euler_matrix(euler_deg)
    mesh.apply_transform(_affine(rot * scale, np.zeros(3)))
    check_size(mesh.extents, scale, str(file))
    try:
        repairs = close_mesh(mesh)
    except MeshImportError as exc:
        raise MeshImportError(f"{file}: {exc}") from None
    # 4: on the table
    xy = {"com": mesh.center_mass[:2], "bbox": mesh.bounds.mean(axis=0)[:2], "source": np.zeros(2)}[center]
    shift = np.array([-xy[0], -xy[1], -mesh.bounds[0, 2]])
    mesh.apply_translation(shift)

    def to_object(points):
        return (np.asarray(points, float) * scale) @ rot.T + shift

    # 5: regions
    groups = obj_groups(file) if any(k == "group" for k, _ in specs.values()) else {}
    surface = surface_points(mesh)
    made = {}
    for rname, (kind, value) in specs.items():
        what = "--part" if rname == part_name else f"--region {rname}="
        region = _region_of(kind, value, groups, to_object, what)
        from forcegrasp.meshes import region_contains

        share = float(region_contains(region.kind, region.center, region.size, surface).mean())
        if share == 0.0:
            lo, hi = mesh.bounds
            raise MeshImportError(
                f"{what} {_spec_text(region)}: the region touches no surface of the mesh (it spans "
                f"x {lo[0]:.3f}..{hi[0]:.3f}, "
                f"y {lo[1]:.3f}..{hi[1]:.3f}, z {lo[2]:.3f}..{hi[2]:.3f} m in the object frame)")
        made[rname] = (region, share)

    # 6: mass properties
    volume = float(mesh.volume)
    density = mass / volume
    inertia = np.asarray(mesh.moment_inertia, float) * density
    com = tuple(float(c) for c in mesh.center_mass)

    # 7: decomposition
    log(f"decomposing {file.name} ({len(mesh.faces)} triangles) with CoACD, threshold {threshold:g}...")
    parts, seconds, cpu_seconds = decompose(mesh.vertices, mesh.faces, threshold, max_parts, **(coacd_options or {}))
    cover = coverage(np.asarray(mesh.vertices), np.asarray(mesh.faces), [p[0] for p in parts])
    from forcegrasp.meshes import region_pieces, write_obj

    # 8: write into a temporary folder inside the assets folder, check, move into place
    (assets / "objects").mkdir(parents=True, exist_ok=True)
    (assets / "meshes").mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".import-{name}-", dir=assets))
    try:
        stage_dir = tmp / "meshes" / name
        stage_dir.mkdir(parents=True)
        (tmp / "objects").mkdir()
        if mesh_dir.is_dir():  # files staged there by hand (a licence notice, the source) stay
            for f in mesh_dir.iterdir():
                if f.is_file() and f.name not in OUTPUTS:
                    shutil.copy2(f, stage_dir / f.name)
        source_name = file.name
        if source_name in OUTPUTS:
            source_name = f"source{file.suffix.lower()}"
        shutil.copy2(file, stage_dir / source_name)
        if notice is not None:
            shutil.copy2(notice, stage_dir / "NOTICE")
        header = (f"{name}: written by forcegrasp object import from {file.name}; object frame, metres")
        write_obj(stage_dir / "visual.obj", [(name, mesh.vertices, mesh.faces)], header)
        write_obj(stage_dir / "parts.obj", [(f"part_{k:03d}", v, f) for k, (v, f) in enumerate(parts)],
                  header + f"\nconvex parts: CoACD threshold {threshold:g}, seed 0")
        for rname, (region, _) in made.items():
            if not region_pieces(stage_dir / "parts.obj", region.kind, region.center, region.size):
                raise MeshImportError(f"--part/--region {rname}: {_spec_text(region)} meets none of the convex parts")
        rel = f"meshes/{name}"
        top = float(mesh.bounds[1, 2])
        main_region = made[part_name][0]
        raw = {
            "name": name,
            "description": description or extra.get("description") or
            f"{file.name} imported as a mesh: {mass:g} kg, functional part {part_name!r}",
            "mass": float(mass),
            "mesh": {
                "source": f"{rel}/{source_name}",
                "source_sha256": hashlib.sha256(file.read_bytes()).hexdigest(),
                "scale": float(scale),
                "euler_deg": [float(a) for a in euler_deg],
                "pos": [round(float(v), 9) + 0.0 for v in shift],  # + 0.0: no -0.0 in the file
                "visual": f"{rel}/visual.obj",
                "parts": f"{rel}/parts.obj",
                "rgba": [float(c) for c in rgba],
                "measured": {
                    "watertight_as_given": watertight,
                    "repairs": repairs,
                    "extents_m": [round(float(e), 6) for e in mesh.extents],
                    "volume_m3": volume,
                    "center_of_mass": [round(c, 6) for c in com],
                    "inertia_at_com": [[float(v) for v in row] for row in inertia],
                    "convex_parts": len(parts),
                    "decomposition": {"tool": f"coacd {_version('coacd')}", "threshold": threshold,
                                      "seconds": round(seconds, 2), "cpu_seconds": round(cpu_seconds, 2),
                                      **{k: round(v, 4) for k, v in cover.items() if k != "samples"}},
                },
            },
            "regions": {r: region.to_json() for r, (region, _) in made.items()},
            "functional_part": [part_name],
            "grasp_hint": extra.get("grasp_hint") or default_hint(main_region, top),
            "view": extra.get("view") or _default_view(mesh),
        }
        staged_file = tmp / "objects" / f"{name}.json"
        staged_file.write_text(json.dumps(raw, indent=2) + "\n")
        try:
            obj = load_object_file(staged_file)
        except ObjectFileError as exc:
            raise MeshImportError(f"the object file would be invalid: {exc}") from exc
        rest = rest_check(obj)
        image, notes = None, []
        if picture:
            try:
                image = object_picture(obj)
            except Exception as exc:  # noqa: BLE001  (no GL here: the object is still good)
                notes.append(f"no picture: rendering failed ({type(exc).__name__}: {exc})")
        _commit(tmp, name, assets)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    result = ImportResult(
        name=name, object_file=object_file, mesh_dir=mesh_dir, extents_m=tuple(float(e) for e in mesh.extents),
        watertight_source=watertight, repairs=repairs, volume_m3=volume, mass_kg=float(mass), center_of_mass=com,
        inertia=inertia, parts=len(parts), decomposition_s=seconds, decomposition_cpu_s=cpu_seconds, coverage=cover,
        region={"name": part_name, "spec": _spec_text(made[part_name][0]),
                "pieces": len(region_pieces(mesh_dir / "parts.obj", main_region.kind, main_region.center,
                                            main_region.size)),
                "surface_share": made[part_name][1]},
        rest=rest,
        notes=notes,
    )
    if image is not None:
        from forcegrasp import docs_dir
        from forcegrasp.render import save_png

        path = Path(picture) if not isinstance(picture, bool) else docs_dir() / "objects" / f"{name}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        save_png(path, image)
        result.picture = path
    return result


def _version(package: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:
        return "?"


def _affine(linear: np.ndarray, shift: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = linear, shift
    return T


def _spec_text(region: Region) -> str:
    if region.group:
        return f"group:{region.group} (box {', '.join(f'{v:.4f}' for v in (*region.center, *region.size))})"
    return f"{region.kind}:{','.join(f'{v:g}' for v in (*region.center, *region.size))}"


def _default_view(mesh) -> dict:
    lo, hi = mesh.bounds
    return {"azimuth": 225.0, "elevation": -25.0, "distance": round(float(max(0.25, 3.0 * np.max(hi - lo))), 3),
            "lookat": [round(float(v), 4) for v in (lo + hi) / 2]}


def _commit(tmp: Path, name: str, assets: Path) -> None:
    """Move the staged mesh folder and object file into place; on any failure put back what was there."""
    mesh_dir, object_file = assets / "meshes" / name, assets / "objects" / f"{name}.json"
    old_dir, old_file = tmp / "old-mesh-dir", tmp / "old-object.json"
    moved = []
    try:
        if mesh_dir.exists():
            os.replace(mesh_dir, old_dir)
            moved.append((old_dir, mesh_dir))
        os.replace(tmp / "meshes" / name, mesh_dir)
        moved.append((mesh_dir, None))
        if object_file.exists():
            os.replace(object_file, old_file)
            moved.append((old_file, object_file))
        os.replace(tmp / "objects" / f"{name}.json", object_file)
    except BaseException:
        for src, back in reversed(moved):
            if back is None:
                shutil.rmtree(src, ignore_errors=True)
            else:
                os.replace(src, back)
        raise


# ------------------------------------------------------------------------------------ checks, pictures
