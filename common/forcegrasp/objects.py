"""Graspable objects as data: one JSON file per object under ``assets/objects/``.

An object is a rigid body built from MuJoCo primitives (box, cylinder, capsule, sphere,
ellipsoid) with one named *functional part* (trigger, handle, button) and a grasp hint that
seeds the labelling optimiser. Adding a fifth object means adding a file, not code.

File format (all lengths in metres, the object frame has z up and its origin on the table
surface under the object)::

    {
      "name": "mug",
      "description": "...",
      "mass": 0.35,                        # kg at mass scale 1
      "friction": [1.0, 0.005, 0.0001],    # optional, MuJoCo sliding/torsional/rolling
      "geoms": [                           # at least one
        {"name": "body", "type": "cylinder", "size": [0.04, 0.05],
         "pos": [0, 0, 0.05], "euler": [0, 0, 0], "rgba": [0.8, 0.8, 0.8, 1]}
      ],
      "functional_part": ["handle_bar"],   # geom names the functional finger must touch
      "grasp_hint": {                      # where the labelling search starts
        "functional_finger": "ff",         # ff, mf, rf, lf or th
        "support_fingers": ["mf", "th"],   # fingertips that should also touch the object
        "rotation": [ARRx, ARRy, ARRz],   # base hinge angles (rad) of the start pose
        "palm_at": [x, y, z],              # object-frame point the palm centre starts at
        "fingers": {"FFJ2": 0.6, ...},     # optional joint start values
        "palm_contact": false              # optional: also pull the palm onto the object
      },
      "view": {                            # optional: the camera of pictures and videos
        "azimuth": 225, "elevation": -25,  # degrees (MuJoCo's free camera: azimuth 0 looks along
        "distance": 0.38,                  # +x, 90 along +y; negative elevation looks down), m
        "lookat": [0.05, -0.03, 0.09]      # the point looked at, from the object's origin (m)
      }
    }

Mesh objects. A file may name a mesh instead of, or beside, primitives (``geoms`` is then
optional). ``forcegrasp object import FILE --name NAME --mass KG`` writes this entry and the files
it names (`forcegrasp.mesh_import`); the paths are relative to the assets folder (the parent of
``objects/``) and stay inside it::

      "mesh": {
        "source": "meshes/mug_mesh/mug.obj",     # the file imported (OBJ or STL), kept as given
        "source_sha256": "...",                  # optional: a changed source is refused (re-import)
        "scale": 1.0,                            # source units -> m
        "euler_deg": [0, 0, -90],                # rotation of the source (x, y, z, degrees), after scaling
        "pos": [0, 0, 0],                        # then this shift (m): lowest vertex on the table (z = 0)
        "visual": "meshes/mug_mesh/visual.obj",  # the repaired, watertight mesh in the object frame (m)
        "parts": "meshes/mug_mesh/parts.obj",    # its convex parts (CoACD), one `o` block each, same frame
        "rgba": [0.9, 0.9, 0.85, 1],             # optional colour of the visual mesh
        "measured": {...}                        # optional, informational: what the import measured
      },
      "regions": {                               # named regions of the mesh's surface (object frame, m)
        "handle": {"box": [x, y, z, hx, hy, hz]},    # centre and half-sizes, or
        "rim": {"sphere": [x, y, z, r]},             # centre and radius; "group": "NAME" records the
      },                                             # OBJ group a box was made from
      "functional_part": ["handle"],             # a region (or primitive geom names, as above)

The visual mesh carries the object's mass (``mass`` × its share of the volume when primitives are
there too), its inertia computed by MuJoCo from the closed mesh at uniform density; the convex parts
collide (and carry no mass). A region's geoms are the convex parts clipped to it (see
`forcegrasp.meshes`): ``functional_part`` and ``grasp_hint.contacts`` may name regions, and
``contacts`` may name ``"mesh"`` (anywhere on the mesh).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from forcegrasp import ASSETS_DIR

#: Number of size parameters per primitive type (MuJoCo's convention).
SIZE_COUNT = {"box": 3, "cylinder": 2, "capsule": 2, "sphere": 1, "ellipsoid": 3}
FINGERS = ("ff", "mf", "rf", "lf", "th")


class ObjectFileError(ValueError):
    """An object name is unknown or its file is malformed (the message names the field)."""


@dataclass(frozen=True)
class GeomSpec:
    name: str
    type: str
    size: tuple[float, ...]
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    euler: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rgba: tuple[float, float, float, float] = (0.7, 0.7, 0.7, 1.0)

    def volume(self) -> float:
        s = self.size
        if self.type == "box":
            return 8.0 * s[0] * s[1] * s[2]
        if self.type == "cylinder":
            return np.pi * s[0] ** 2 * 2.0 * s[1]
        if self.type == "capsule":
            return np.pi * s[0] ** 2 * 2.0 * s[1] + 4.0 / 3.0 * np.pi * s[0] ** 3
        if self.type == "sphere":
            return 4.0 / 3.0 * np.pi * s[0] ** 3
        return 4.0 / 3.0 * np.pi * s[0] * s[1] * s[2]  # ellipsoid


@dataclass(frozen=True)
class GraspHint:
    functional_finger: str
    support_fingers: tuple[str, ...]
    rotation: tuple[float, float, float]
    palm_at: tuple[float, float, float]
    fingers: dict[str, float] = field(default_factory=dict)
    palm_contact: bool = False
    #: finger -> the parts its distal phalanx rests on (the grasp's holding contacts)
    contacts: dict[str, tuple[str, ...]] = field(default_factory=dict)
    #: finger (its tip) or finger.segment (proximal, middle, distal: that phalanx's centre) -> a
    #: point in the object's frame (m) it should reach: which face of a part it rests on, or that
    #: it passes through an opening
    targets: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    #: solve the targets first (a finger threaded through an opening), then add the holding contacts
    two_stage: bool = False
    #: fingers that keep their goal shape at the pre-grasp (a finger that slides into an opening)
    keep_shape: tuple[str, ...] = ()
    #: pre-grasp retreat directions to try first (names of ``labeling.RETREAT_DIRECTIONS``)
    approach: tuple[str, ...] = ()
    #: the grasp in words: what a person would do (``forcegrasp label`` prints it)
    grasp: str = ""


@dataclass(frozen=True)
class View:
    """Where pictures and videos of an object are taken from (a MuJoCo free camera): it looks at
    the object's origin plus ``lookat`` (m, world axes), from ``distance`` m away, turned
    ``azimuth`` degrees about z (0: looking along +x, 90: along +y) and ``elevation`` degrees
    (negative: from above). Each object file chooses one that shows its functional contact."""

    azimuth: float = 200.0
    elevation: float = -25.0
    distance: float = 0.55
    lookat: tuple[float, float, float] = (0.0, 0.0, 0.08)


#: bounds of the ``view`` fields: (low, high), inclusive
VIEW_BOUNDS = {"azimuth": (-360.0, 360.0), "elevation": (-90.0, 90.0), "distance": (0.05, 5.0), "lookat": (-1.0, 1.0)}


@dataclass(frozen=True)
class Region:
    """Part of a mesh's surface: the surface inside a box (``size``: half-sizes) or a sphere
    (``size``: [radius]) in object coordinates (m)."""

    kind: str
    center: tuple[float, float, float]
    size: tuple[float, ...]
    group: str = ""  # the OBJ group a box was made from (informational)

    def to_json(self) -> dict:
        out = {self.kind: [*self.center, *self.size]}
        if self.group:
            out["group"] = self.group
        return out


#: values per region kind: centre (3) and half-sizes (3) or radius (1)
REGION_COUNT = {"box": 6, "sphere": 4}
MESH_SUFFIXES = (".obj", ".stl")
MESH_PART = "mesh"  # the part name meaning "anywhere on the mesh" (its convex parts)


@dataclass(frozen=True)
class MeshSpec:
    """The ``mesh`` entry: files resolved to absolute paths, the rest as written."""

    visual: Path
    parts: Path
    source: str
    scale: float = 1.0
    euler_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rgba: tuple[float, float, float, float] = (0.85, 0.85, 0.8, 1.0)
    measured: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    description: str
    mass: float
    geoms: tuple[GeomSpec, ...]
    functional_part: tuple[str, ...]
    grasp_hint: GraspHint
    friction: tuple[float, float, float] = (1.0, 0.005, 0.0001)
    path: Path | None = None
    view: View = View()
    mesh: MeshSpec | None = None
    regions: dict[str, Region] = field(default_factory=dict)

    def part_names(self) -> list[str]:
        """What ``functional_part`` and ``grasp_hint.contacts`` may name."""
        return [g.name for g in self.geoms] + list(self.regions) + ([MESH_PART] if self.mesh else [])


def objects_dir() -> Path:
    return ASSETS_DIR / "objects"


def list_objects() -> list[str]:
    """Names of the objects that have a file under ``assets/objects``."""
    return sorted(p.stem for p in objects_dir().glob("*.json"))


def load_object(name: str) -> ObjectSpec:
    """Load and validate one object by name; unknown names list the valid ones."""
    path = objects_dir() / f"{name}.json"
    if not name or "/" in name or "\\" in name or name.startswith(".") or not path.is_file():
        raise ObjectFileError(f"unknown object {name!r}; valid objects: {', '.join(list_objects())}")
    return load_object_file(path)


def load_object_file(path: Path) -> ObjectSpec:
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ObjectFileError(f"{path}: not readable JSON ({exc})") from exc
    return parse_object(raw, source=str(path), path=Path(path))


def _field(raw: dict, key: str, source: str):
    if not isinstance(raw, dict) or key not in raw:
        raise ObjectFileError(f"{source}: missing field {key!r}")
    return raw[key]


def _floats(value, n: int | None, what: str, source: str) -> tuple[float, ...]:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ObjectFileError(f"{source}: field {what!r} must be numbers, got {value!r}") from None
    if arr.ndim != 1 or (n is not None and arr.size != n) or not np.all(np.isfinite(arr)):
        want = f"{n} finite numbers" if n is not None else "a list of finite numbers"
        raise ObjectFileError(f"{source}: field {what!r} must be {want}, got {value!r}")
    return tuple(float(v) for v in arr)


def parse_view(raw, source: str = "<object>") -> View:
    """The optional ``view`` field: a map with azimuth, elevation, distance (numbers) and lookat
    ([x, y, z]); fields left out keep `View`'s defaults; anything else names the field."""
    if raw is None:
        return View()
    if not isinstance(raw, dict):
        raise ObjectFileError(f"{source}: field 'view' must be a map with {', '.join(VIEW_BOUNDS)}, got {raw!r}")
    unknown = sorted(set(raw) - set(VIEW_BOUNDS))
    if unknown:
        raise ObjectFileError(f"{source}: field 'view' has unknown keys {unknown}; allowed: {', '.join(VIEW_BOUNDS)}")
    values = {}
    for key, (lo, hi) in VIEW_BOUNDS.items():
        if key not in raw:
            continue
        value = raw[key]
        if key == "lookat":
            got = _floats(value, 3, "view.lookat", source)
            if not all(lo <= v <= hi for v in got):
                raise ObjectFileError(f"{source}: field 'view.lookat' must be 3 numbers in [{lo:g}, {hi:g}] m, "
                                      f"got {value!r}")
        else:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (lo <= value <= hi):
                unit = "m" if key == "distance" else "degrees"
                raise ObjectFileError(f"{source}: field 'view.{key}' must be a number in [{lo:g}, {hi:g}] {unit}, "
                                      f"got {value!r}")
            got = float(value)
        values[key] = got
    return View(**values)


def parse_object(raw: dict, source: str = "<object>", path: Path | None = None) -> ObjectSpec:
    """Validate a decoded object file; every error names the offending field."""
    name = _field(raw, "name", source)
    if not isinstance(name, str) or not name.isidentifier():
        raise ObjectFileError(f"{source}: field 'name' must be an identifier, got {name!r}")
    mass = _field(raw, "mass", source)
    if not isinstance(mass, (int, float)) or not np.isfinite(mass) or mass <= 0:
        raise ObjectFileError(f"{source}: field 'mass' must be a positive number (kg), got {mass!r}")
    assets = Path(path).resolve().parent.parent if path is not None else ASSETS_DIR
    from forcegrasp.object_meshes import parse_mesh, parse_regions  # they build on this module's types

    mesh = parse_mesh(raw["mesh"], source, assets) if isinstance(raw, dict) and "mesh" in raw else None
    geoms_raw = raw.get("geoms", []) if mesh is not None else _field(raw, "geoms", source)
    if not isinstance(geoms_raw, list) or (not geoms_raw and mesh is None):
        raise ObjectFileError(f"{source}: field 'geoms' must be a non-empty list (or the file needs a 'mesh')")
    geoms = []
    for i, g in enumerate(geoms_raw):
        where = f"geoms[{i}]"
        gname = _field(g, "name", f"{source}: {where}")
        gtype = _field(g, "type", f"{source}: {where}")
        if gtype not in SIZE_COUNT:
            raise ObjectFileError(
                f"{source}: field '{where}.type' must be one of {sorted(SIZE_COUNT)}, got {gtype!r}"
            )
        size = _floats(_field(g, "size", f"{source}: {where}"), SIZE_COUNT[gtype], f"{where}.size", source)
        if min(size) <= 0:
            raise ObjectFileError(f"{source}: field '{where}.size' must be positive, got {list(size)}")
        geoms.append(
            GeomSpec(
                name=str(gname),
                type=gtype,
                size=size,
                pos=_floats(g.get("pos", [0, 0, 0]), 3, f"{where}.pos", source),
                euler=_floats(g.get("euler", [0, 0, 0]), 3, f"{where}.euler", source),
                rgba=_floats(g.get("rgba", [0.7, 0.7, 0.7, 1]), 4, f"{where}.rgba", source),
            )
        )
    names = [g.name for g in geoms]
    if len(set(names)) != len(names):
        raise ObjectFileError(f"{source}: field 'geoms' has duplicate names {names}")
    if mesh is not None and MESH_PART in names:
        raise ObjectFileError(f"{source}: field 'geoms': the name {MESH_PART!r} is the mesh's own with a 'mesh'")
    regions = parse_regions(raw.get("regions", {}), source, mesh is not None, names)
    names = names + list(regions) + ([MESH_PART] if mesh is not None else [])
    part = _field(raw, "functional_part", source)
    part = (part,) if isinstance(part, str) else tuple(part) if isinstance(part, list) else None
    if not part or any(p not in names for p in part):
        raise ObjectFileError(
            f"{source}: field 'functional_part' must name geoms or regions among {names}, "
            f"got {raw['functional_part']!r}"
        )
    hint_raw = _field(raw, "grasp_hint", source)
    finger = _field(hint_raw, "functional_finger", f"{source}: grasp_hint")
    support = tuple(hint_raw.get("support_fingers", []))
    for f in (finger, *support):
        if f not in FINGERS:
            raise ObjectFileError(f"{source}: field 'grasp_hint' finger {f!r} not one of {FINGERS}")
    fingers = hint_raw.get("fingers", {})
    if not isinstance(fingers, dict):
        raise ObjectFileError(f"{source}: field 'grasp_hint.fingers' must be a map joint -> angle")
    contacts_raw = hint_raw.get("contacts", {})
    if not isinstance(contacts_raw, dict):
        raise ObjectFileError(f"{source}: field 'grasp_hint.contacts' must be a map finger -> list of parts")
    contacts = {}
    for f, parts in contacts_raw.items():
        parts = (parts,) if isinstance(parts, str) else tuple(parts) if isinstance(parts, list) else None
        if f not in FINGERS or f == finger or not parts or any(p not in names for p in parts):
            raise ObjectFileError(f"{source}: field 'grasp_hint.contacts.{f}' must map a finger of {FINGERS} "
                                  f"(not the functional one) to parts among {names}, got {contacts_raw[f]!r}")
        contacts[f] = parts
    targets_raw = hint_raw.get("targets", {})
    segments = ("proximal", "middle", "distal")
    if not isinstance(targets_raw, dict) or any(
            f.split(".")[0] not in FINGERS or (f.count(".") and f.split(".", 1)[1] not in segments) for f in targets_raw):
        raise ObjectFileError(f"{source}: field 'grasp_hint.targets' must map fingers of {FINGERS} (or "
                              f"finger.segment, segment one of {segments}) to points [x, y, z]")
    targets = {f: _floats(v, 3, f"grasp_hint.targets.{f}", source) for f, v in targets_raw.items()}
    approach = hint_raw.get("approach", [])
    if not isinstance(approach, list) or not all(isinstance(a, str) for a in approach):
        raise ObjectFileError(f"{source}: field 'grasp_hint.approach' must be a list of direction names")
    hint = GraspHint(
        functional_finger=finger,
        support_fingers=support,
        rotation=_floats(_field(hint_raw, "rotation", f"{source}: grasp_hint"), 3, "grasp_hint.rotation", source),
        palm_at=_floats(_field(hint_raw, "palm_at", f"{source}: grasp_hint"), 3, "grasp_hint.palm_at", source),
        fingers={str(k): float(v) for k, v in fingers.items()},
        palm_contact=bool(hint_raw.get("palm_contact", False)),
        contacts=contacts,
        targets=targets,
        two_stage=bool(hint_raw.get("two_stage", False)),
        keep_shape=tuple(f for f in hint_raw.get("keep_shape", []) if f in FINGERS),
        approach=tuple(approach),
        grasp=str(hint_raw.get("grasp", "")),
    )
    friction = _floats(raw.get("friction", [1.0, 0.005, 0.0001]), 3, "friction", source)
    return ObjectSpec(
        name=name,
        description=str(raw.get("description", "")),
        mass=float(mass),
        geoms=tuple(geoms),
        functional_part=part,
        grasp_hint=hint,
        friction=friction,
        path=path,
        view=parse_view(raw.get("view"), source),
        mesh=mesh,
        regions=regions,
    )
