"""The `forcegrasp` command line: one entry point, one sub-command per job."""

from __future__ import annotations

import argparse
import json
import sys


def cmd_label(args) -> int:
    from forcegrasp.labeling import label_object
    from forcegrasp.labels import save_label
    from forcegrasp.objects import ObjectFileError, load_object

    try:
        obj = load_object(args.object)
    except ObjectFileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    label = label_object(obj, mass_scale=args.mass_scale, seed=args.seed)
    checks = label.checks
    ok = label_ok(checks)
    print(json.dumps(checks, indent=2))
    print(
        f"functional finger touches {'/'.join(obj.functional_part)}: {checks['functional_contact']} "
        f"(gap {checks['functional_gap_m'] * 1000:.1f} mm)\n"
        f"max penetration while holding: {checks['max_penetration_m'] * 1000:.2f} mm (limit 2 mm)\n"
        f"object moved while holding 1 s on the table: {checks['object_moved_m'] * 1000:.2f} mm (limit 10 mm)\n"
        f"the grasp holds without the table (1x mass): {checks['holds']} (moved {checks['hold_moved_in_palm_m'] * 1000:.1f} mm "
        f"in the palm, limit 10 mm; in contact: {', '.join(checks['hold_fingers']) or 'nothing'}; thumb and two more needed)\n"
        f"... at {checks['hold_mass_scale']:g}x mass: {checks['holds_heavy']} (moved {checks['hold_heavy_moved_in_palm_m'] * 1000:.1f} mm)\n"
        f"pre-grasp clear over the whole jitter square: {checks['pregrasp_clear_over_square']} "
        f"(closest {checks['pregrasp_clearance_m'] * 1000:.1f} mm), palm {checks['pregrasp_palm_distance_m'] * 1000:.0f} mm "
        f"from the object (about 20 mm or more)\n"
        f"pre-grasp palm inside the env's palm tolerance at every placement: {checks['pregrasp_within_palm_tolerance']} "
        f"(worst {checks['pregrasp_worst_palm_error_m'] * 1000:.0f} mm from its goal, limit 95 mm)"
    )
    if args.dry_run:
        return 0 if ok else 1
    if not ok:
        print("checks failed: label not written", file=sys.stderr)
        return 1

    path = save_label(label, args.out)
    print(f"wrote {path}")
    picture = _save_grasp_picture(obj.name, label)
    print(f"wrote {picture} (top row: pre-grasp G0, bottom row: goal grasp Gg)")
    return 0


def label_ok(checks: dict) -> bool:
    """The checks a label must pass to be written (see forcegrasp.label_checks)."""
    return bool(checks["functional_contact"] and checks["max_penetration_m"] < 0.002 and checks["object_moved_m"] < 0.01
                and checks["holds"] and checks["pregrasp_clear_over_square"]
                and checks["pregrasp_within_palm_tolerance"])


def _save_grasp_picture(name: str, label=None):
    from forcegrasp import docs_dir
    from forcegrasp.render import grasp_picture, save_png

    path = docs_dir() / "grasps" / f"{name}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    save_png(path, grasp_picture(name, label))
    return path


def cmd_picture(args) -> int:
    from forcegrasp.objects import list_objects

    for name in args.objects or list_objects():
        print(f"wrote {_save_grasp_picture(name)}")
    return 0


def cmd_objects(args) -> int:
    from forcegrasp.objects import list_objects, load_object

    for name in list_objects():
        print(f"{name:14s} {load_object(name).description}")
    return 0


def cmd_certs(args) -> int:
    from forcegrasp.certs import CertsError, make_credentials

    try:
        written = make_credentials(args.dir, actors=args.actors, hosts=tuple(args.host), add=tuple(args.add),
                                   days=args.days)
    except CertsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.dir}: wrote {', '.join(written) or 'nothing new'} (CA: {args.dir}/ca.pem; keep ca-key.pem here)")
    print(f"  run a service with --set network.credentials={args.dir} and tls/ endpoints (docs/security.md);")
    print(f"  an actor on a spare machine needs only {args.dir}/actor-<id>/")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="forcegrasp", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("label", help="find the goal grasp and pre-grasp of an object and write its label")
    p.add_argument("object", help="object name (a file under assets/objects/)")
    p.add_argument("--mass-scale", type=float, default=5.0, help="mass scale for the approach check")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="label path (default assets/labels/OBJECT.json)")
    p.add_argument("--dry-run", action="store_true", help="run and check, write nothing")
    p.set_defaults(func=cmd_label)

    for name, (_, help_text) in {**SERVICES, **TOOLS}.items():
        sub.add_parser(name, help=help_text + " (see forcegrasp %s --help)" % name, add_help=False)

    p = sub.add_parser("picture", help="render the labelled grasps of objects to docs/grasps/")
    p.add_argument("objects", nargs="*", help="object names (default: all)")
    p.set_defaults(func=cmd_picture)

    p = sub.add_parser("certs", help="make a development CA and credentials per service for a secure cluster")
    p.add_argument("dir", help="output folder (an existing CA there is reused; existing identities are kept)")
    p.add_argument("--actors", type=int, default=2, help="actor identities actor-0 ... actor-<N-1>")
    p.add_argument("--host", action="append", default=[], help="extra host name or IP the learner is reached at")
    p.add_argument("--add", action="append", default=[], help="one more identity, e.g. actor-7")
    p.add_argument("--days", type=int, default=365, help="validity of the certificates")
    p.set_defaults(func=cmd_certs)

    p = sub.add_parser("objects", help="list the objects")
    p.set_defaults(func=cmd_objects)
    return parser


#: Sub-commands that own their whole argument list (they take the shared --config/--set options).
SERVICES = {
    "up": ("forcegrasp.cli.up", "start learner, actors and evaluator as local processes on loopback"),
    "learner": ("forcegrasp_learner.learner", "run the SAC learner service"),
    "actor": ("forcegrasp_actor.actor", "run one actor service (point it at a learner with --set)"),
    "evaluator": ("forcegrasp_evaluator.evaluator", "run the evaluator service (top-k checkpoints, best policy)"),
}

#: Other sub-commands that own their argument list.
TOOLS = {
    "best": ("forcegrasp_evaluator.client", "fetch the evaluator's best policy: forcegrasp best --out FILE"),
    "serve": ("forcegrasp_evaluator.serve", "serve a shipped policy as the best-policy endpoint (HTTP and Zenoh)"),
    "replay": ("forcegrasp.cli.replay", "render an evaluator episode log (.mcap) to an image strip or video"),
    "plot": ("forcegrasp.cli.plot", "training curves of one or several runs as one PNG"),
    "train": ("forcegrasp.cli.train", "train in this process: the same roles and files as `up`, no network (resumable)"),
    "experiment": ("forcegrasp.cli.experiment", "train one configuration for a wall-clock budget, test it at fixed marks"),
    "online-check": ("forcegrasp.cli.online_check", "does a frozen policy's online success match its offline tests?"),
    "eval": ("forcegrasp.cli.policy_eval", "test a policy on held-out placements, sweeping mass, torque noise..."),
    "ship": ("forcegrasp.cli.ship", "copy an experiment's picked policy into assets/policies/ with its record"),
    "report": ("forcegrasp.cli.report", "the paper's experiments on the shipped policies: docs/results.md and figures"),
    "export": ("forcegrasp.cli.export", "export a policy file to ONNX: forcegrasp export FILE --onnx OUT.onnx"),
    "object": ("forcegrasp.cli.object", "bring your own object: forcegrasp object import FILE --name NAME --mass KG --part ..."),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and (argv[0] in SERVICES or argv[0] in TOOLS):
        import importlib

        from forcegrasp.config import ConfigError
        from forcegrasp.objects import ObjectFileError

        try:
            module = (SERVICES.get(argv[0]) or TOOLS[argv[0]])[0]
            return int(importlib.import_module(module).main(argv[1:]) or 0)
        except (ConfigError, ObjectFileError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)

