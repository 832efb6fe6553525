"""``forcegrasp object import FILE --name NAME --mass KG [--scale S] [--part SPEC]``: bring your own
object (a mesh file) into the assets; see `forcegrasp.mesh_import` for each step and its refusals."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _floats3(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 3 numbers rx,ry,rz, got {text!r}") from None
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected 3 numbers rx,ry,rz, got {text!r}")
    return values


def _region(text: str) -> tuple[str, str]:
    name, sep, spec = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected NAME=box:...|sphere:...|group:..., got {text!r}")
    return name.strip(), spec.strip()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="forcegrasp object", description="objects of the assets folder")
    sub = parser.add_subparsers(dest="action", required=True)
    p = sub.add_parser(
        "import", help="import a mesh file (OBJ, STL) as an object: convex parts, mass properties, functional part",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", type=Path, help="the mesh file (OBJ or STL)")
    p.add_argument("--name", required=True, help="object name (an identifier): assets/objects/NAME.json")
    p.add_argument("--mass", required=True, type=float, help="mass in kg (inertia from the mesh at uniform density)")
    p.add_argument("--scale", type=float, default=1.0, help="source units to metres (0.001 for a file in mm)")
    p.add_argument("--part", required=True,
                   help="functional part: box:x,y,z,hx,hy,hz | sphere:x,y,z,r (object frame, m) | group:NAME (OBJ)")
    p.add_argument("--part-name", default="functional", help="the functional part's name (default: functional)")
    p.add_argument("--region", action="append", type=_region, default=[], metavar="NAME=SPEC",
                   help="another named region for the grasp hint's contacts (repeatable)")
    p.add_argument("--euler", type=_floats3, default=(0.0, 0.0, 0.0), metavar="RX,RY,RZ",
                   help="turn the source about x, y, z (degrees) after scaling: z must end up upwards")
    p.add_argument("--center", choices=("com", "bbox", "source"), default="com",
                   help="what sits over the object's origin: centre of mass, bounding-box centre, source origin")
    p.add_argument("--hint", type=Path, help="JSON: a grasp_hint map (optionally with view, description)")
    p.add_argument("--description", default="")
    p.add_argument("--notice", type=Path, help="a licence notice to keep beside the mesh (copied as NOTICE)")
    p.add_argument("--threshold", type=float, default=0.05, help="CoACD concavity threshold (smaller: more parts)")
    p.add_argument("--max-parts", type=int, default=-1, help="at most this many convex parts (-1: no limit)")
    p.add_argument("--force", action="store_true", help="replace an existing object of that name")
    p.add_argument("--no-picture", action="store_true", help="skip the rendering")
    p.add_argument("--picture", type=Path, help="where the picture goes (default docs/objects/NAME.png)")
    p.set_defaults(func=cmd_import)
    return parser


def cmd_import(args) -> int:
    from forcegrasp.mesh_import import MeshImportError, import_mesh

    try:
        result = import_mesh(
            args.file, args.name, args.mass, scale=args.scale, part=args.part, part_name=args.part_name,
            regions=dict(args.region), euler_deg=args.euler, center=args.center, hint=args.hint,
            description=args.description, notice=args.notice, threshold=args.threshold, max_parts=args.max_parts,
            force=args.force, picture=False if args.no_picture else (args.picture or True),
        )
    except MeshImportError as exc:
        print(f"error: {exc}", file=sys.stderr)
        print("nothing was written", file=sys.stderr)
        return 2
    print(result.summary())
    print(f"next: forcegrasp label {result.name}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
