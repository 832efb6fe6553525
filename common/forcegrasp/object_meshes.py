"""The mesh and region entries of an object file: a mesh object's files (inside the assets folder,
unchanged since import) and the named boxes and spheres its functional part and grasp hint refer
to. Parsed like every other field of `forcegrasp.objects`, with an ObjectFileError naming it."""

from __future__ import annotations

import hashlib
from pathlib import Path, PurePosixPath

import numpy as np

from forcegrasp import ASSETS_DIR
from forcegrasp.objects import (MESH_PART, MESH_SUFFIXES, REGION_COUNT, MeshSpec, ObjectFileError, Region, _field,
                                _floats)


def _asset_file(value, what: str, source: str, assets: Path, suffixes: tuple[str, ...]) -> Path:
    """A path relative to the assets folder that stays inside it and names an existing file."""
    if not isinstance(value, str) or not value:
        raise ObjectFileError(f"{source}: field {what!r} must be a path relative to the assets folder, got {value!r}")
    rel = PurePosixPath(value)
    if rel.is_absolute() or ".." in rel.parts or "\\" in value:
        raise ObjectFileError(f"{source}: field {what!r} must be a path inside the assets folder, got {value!r}")
    if rel.suffix.lower() not in suffixes:
        raise ObjectFileError(f"{source}: field {what!r} must name a {' or '.join(suffixes)} file, got {value!r}")
    full = assets / rel
    if not full.is_file():
        raise ObjectFileError(f"{source}: field {what!r}: no file {full} (was the object imported with "
                              "`forcegrasp object import`?)")
    return full


def parse_mesh(raw, source: str = "<object>", assets: Path | None = None) -> MeshSpec:
    """The ``mesh`` entry (see the module docstring); files are resolved under ``assets``."""
    assets = ASSETS_DIR if assets is None else Path(assets)
    if not isinstance(raw, dict):
        raise ObjectFileError(f"{source}: field 'mesh' must be a map with visual, parts, source, scale...")
    allowed = {"source", "source_sha256", "scale", "euler_deg", "pos", "visual", "parts", "rgba", "measured"}
    unknown = sorted(set(raw) - allowed)
    if unknown:
        raise ObjectFileError(f"{source}: field 'mesh' has unknown keys {unknown}; "
                              f"allowed: {', '.join(sorted(allowed))}")
    visual = _asset_file(_field(raw, "visual", f"{source}: mesh"), "mesh.visual", source, assets, (".obj",))
    parts = _asset_file(_field(raw, "parts", f"{source}: mesh"), "mesh.parts", source, assets, (".obj",))
    src = raw.get("source", "")
    if src:
        src_path = _asset_file(src, "mesh.source", source, assets, MESH_SUFFIXES)
        digest = raw.get("source_sha256")
        if digest and hashlib.sha256(src_path.read_bytes()).hexdigest() != digest:
            raise ObjectFileError(f"{source}: field 'mesh.source': {src} changed since it was imported (sha256 "
                                  "differs): import it again with `forcegrasp object import`")
    scale = raw.get("scale", 1.0)
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not np.isfinite(scale) or scale <= 0:
        raise ObjectFileError(f"{source}: field 'mesh.scale' must be a positive number, got {scale!r}")
    measured = raw.get("measured", {})
    if not isinstance(measured, dict):
        raise ObjectFileError(f"{source}: field 'mesh.measured' must be a map")
    return MeshSpec(
        visual=visual,
        parts=parts,
        source=str(src),
        scale=float(scale),
        euler_deg=_floats(raw.get("euler_deg", [0, 0, 0]), 3, "mesh.euler_deg", source),
        pos=_floats(raw.get("pos", [0, 0, 0]), 3, "mesh.pos", source),
        rgba=_floats(raw.get("rgba", [0.85, 0.85, 0.8, 1]), 4, "mesh.rgba", source),
        measured=dict(measured),
    )


def parse_region(raw, what: str = "region", source: str = "<object>") -> Region:
    """One region: ``{"box": [x, y, z, hx, hy, hz]}`` or ``{"sphere": [x, y, z, r]}`` (m), optional
    ``"group"`` (the OBJ group it was made from)."""
    if not isinstance(raw, dict) or len(set(raw) & set(REGION_COUNT)) != 1 or set(raw) - {*REGION_COUNT, "group"}:
        raise ObjectFileError(f"{source}: field {what!r} must be {{\"box\": [x, y, z, hx, hy, hz]}} or "
                              f"{{\"sphere\": [x, y, z, r]}} (m), got {raw!r}")
    kind = next(k for k in REGION_COUNT if k in raw)
    values = _floats(raw[kind], REGION_COUNT[kind], f"{what}.{kind}", source)
    if min(values[3:]) <= 0:
        raise ObjectFileError(f"{source}: field '{what}.{kind}' must have positive sizes, got {list(values)}")
    group = raw.get("group", "")
    if not isinstance(group, str):
        raise ObjectFileError(f"{source}: field '{what}.group' must be a group name")
    return Region(kind=kind, center=values[:3], size=values[3:], group=group)


def parse_regions(raw, source: str, has_mesh: bool, geom_names: list[str]) -> dict[str, Region]:
    if not raw:
        return {}
    if not has_mesh:
        raise ObjectFileError(f"{source}: field 'regions' needs a 'mesh' (regions are parts of a mesh's surface)")
    if not isinstance(raw, dict):
        raise ObjectFileError(f"{source}: field 'regions' must be a map name -> region")
    out = {}
    for name, value in raw.items():
        if not isinstance(name, str) or not name.isidentifier() or name in geom_names or name == MESH_PART:
            raise ObjectFileError(f"{source}: field 'regions' key {name!r} must be an identifier other than "
                                  f"{MESH_PART!r} and the geom names {geom_names}")
        out[name] = parse_region(value, f"regions.{name}", source)
    return out
