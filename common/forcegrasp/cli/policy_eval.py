"""``forcegrasp eval POLICY``: test a trained policy on held-out placements, sweeping one env setting.

This is how the paper tests a policy after training:
- lighter objects: ``--sweep mass_scale=5,1,0.5 --env object_tolerance=0.03``;
- joint-torque noise: ``--sweep torque_noise_std=0,0.1,0.2,...,1``.

POLICY is a policy file, or a run directory, whose evaluator's best checkpoint is then used. The
object and the force-feedback setting come from the policy's metadata. The placements are the
``"test"`` stream, drawn like the evaluator's but never used to select a checkpoint, so the
figures are not inflated by the selection. Every sweep value sees the same placements (unless
the jitter itself is swept). The policy acts deterministically (tanh of the mean).

A policy of several objects (``env.objects``: its file records the set) is tested on each of them,
one row per object and setting, the table ending with the worst object's figures; ``--object NAME``
(repeatable) picks some. ``--unseen NAME`` (repeatable) also tests it, zero-shot, on an object it
was not trained on (the leave-one-out test); such rows say so and stay out of the worst object's.

``--video OUT.gif`` (or ``.mp4``) renders instead of scoring: one episode on the first held-out
placement, seen by the object's camera; ``--video DIR`` writes ``DIR/test-000.gif``... for the
first ``--video-count`` placements (the same placements, in the same order, as the scores).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

from forcegrasp.multi_object import aggregate, policy_objects

SWEEPABLE = ("mass_scale", "torque_noise_std", "jitter", "object_tolerance", "palm_tolerance")


def resolve_policy(path: Path) -> Path:
    """A policy file as given, a run directory's best checkpoint (its evaluator's top k), or the name
    of a shipped policy (``mug-ff-s0``: assets/policies/, installed with the package)."""
    from forcegrasp import ASSETS_DIR
    from forcegrasp.rundir import RunDir

    if path.is_file():
        return path
    best = RunDir(path).best_policy() if path.is_dir() else None
    if best is not None:
        return best
    shipped = ASSETS_DIR / "policies" / f"{path.name}.safetensors"
    if len(path.parts) == 1 and shipped.is_file():
        return shipped
    raise FileNotFoundError(f"{path}: neither a policy file, a run directory with an evaluated best checkpoint, nor "
                            f"a shipped policy ({', '.join(sorted(p.stem for p in (ASSETS_DIR / 'policies').glob('*.safetensors')))})")


def parse_setting(text: str, many: bool) -> tuple[str, list[float]]:
    key, sep, values = text.partition("=")
    key = key.strip().removeprefix("env.")
    if not sep or key not in SWEEPABLE:
        raise ValueError(f"{text!r}: expected KEY=VALUE{',VALUE...' if many else ''} with KEY one of {', '.join(SWEEPABLE)}")
    try:
        numbers = [float(v) for v in values.split(",")] if many else [float(values)]
    except ValueError:
        raise ValueError(f"{text!r}: values must be numbers") from None
    return key, numbers


def evaluate_settings(policy_path: Path, episodes: int, seed: int, fixed: dict, sweep: tuple[str, list[float]] | None,
                log=print, log_dir: Path | None = None, objects: list[str] | None = None,
                unseen: list[str] | None = None) -> list[dict]:
    """One row per object and sweep value: success rate, mean return and failure counts over the
    placements (``objects``: which of the policy's objects, default all; ``unseen``: objects it was
    not trained on, tested zero-shot)."""
    from forcegrasp.evaluation import placements, run_episode

    policy = _load_policy(policy_path)
    meta = policy.metadata
    key, values = sweep if sweep else (None, [None])
    names = _objects_to_test(policy, objects) + _unseen_objects(policy, unseen or [])
    trained = set(policy_objects(meta))
    rows = []
    for obj, value in ((o, v) for o in names for v in values):
        kwargs = dict(fixed)
        if key is not None:
            kwargs[key] = value
        env = _env_for(policy, policy_path, kwargs, obj)
        t0 = time.perf_counter()
        folder = None if log_dir is None else log_dir / (obj if len(names) > 1 else "") / (
            f"{key}-{value:g}" if key else "as-given")
        results = [run_episode(env, policy, p, _logger(folder, env, p, meta, policy_path))
                   for p in placements(seed, episodes, env.jitter, "test", clear=env.is_clear)]
        row = {"object": obj, "zero_shot": obj not in trained, "force_feedback": meta.force_feedback,
               "setting": key, "value": value, "episodes": len(results),
               "success_rate": sum(r.success for r in results) / len(results),
               "mean_return": sum(r.ret for r in results) / len(results),
               "failures": dict(Counter(r.failure for r in results if not r.success)),
               # a policy trained under randomisation is tested under it unless a setting fixes it
               "env": {k: (list(v) if isinstance(v, tuple) else v) for k in (
                   "mass_scale", "torque_noise_std", "mass_scale_range", "torque_noise_range", "jitter", "jitter_range",
                   "object_tolerance") for v in [getattr(env, k)]},
               "seconds": round(time.perf_counter() - t0, 1)}
        rows.append(row)
        log(f"{obj + ': ' if len(names) > 1 else ''}{key or 'settings'} = "
            f"{value if key else kwargs or 'defaults'}: success {row['success_rate']:.0%}, "
            f"return {row['mean_return']:.1f}, failures {row['failures']} ({row['seconds']} s)")
    return rows


def _load_policy(policy_path: Path):
    from forcegrasp.policy import Policy

    policy = Policy.load(policy_path)
    if not policy_objects(policy.metadata):
        raise ValueError(f"{policy_path}: the policy's metadata names no object")
    return policy


def _unseen_objects(policy, unseen: list[str]) -> list[str]:
    """Objects to test zero-shot: known objects the policy was not trained on."""
    from forcegrasp.objects import list_objects

    trained = policy_objects(policy.metadata)
    for name in unseen:
        if name not in list_objects():
            raise ValueError(f"--unseen {name}: unknown object (known: {', '.join(list_objects())})")
        if name in trained:
            raise ValueError(f"--unseen {name}: the policy was trained on it (use --object)")
    return list(dict.fromkeys(unseen))


def _objects_to_test(policy, wanted: list[str] | None) -> list[str]:
    """The policy's objects (``extra["objects"]`` or its one object), or those of them ``wanted``."""
    trained = policy_objects(policy.metadata)
    unknown = sorted(set(wanted or ()) - set(trained))
    if unknown:
        raise ValueError(f"--object {', '.join(unknown)}: the policy was trained on {', '.join(trained)}")
    return [o for o in trained if o in wanted] if wanted else trained


def _env_for(policy, policy_path: Path, kwargs: dict, obj: str | None = None):
    """The env ``policy`` was trained for (on ``obj``, default its first object), with the test
    settings ``kwargs``."""
    from forcegrasp.env import FunctionalGraspEnv

    meta = policy.metadata
    env = FunctionalGraspEnv.for_policy(meta, obj or policy_objects(meta)[0], **kwargs)
    if env.observation_space.shape[0] != meta.obs_dim:
        raise ValueError(f"{policy_path}: policy expects {meta.obs_dim} observations, the env gives "
                         f"{env.observation_space.shape[0]}")
    return env


def video_targets(out: Path, count: int, fmt: str) -> list[Path]:
    """``[out]`` for a .gif or .mp4 file name; ``out/test-000.<fmt>``... for a directory (an existing
    one, or a name without a suffix)."""
    from forcegrasp.video import VIDEO_SUFFIXES

    if out.is_dir() or not out.suffix:
        if count < 1:
            raise ValueError("--video-count must be at least 1")
        return [out / f"test-{i:03d}.{fmt}" for i in range(count)]
    if out.suffix.lower() not in VIDEO_SUFFIXES:
        raise ValueError(f"--video {out}: use a .gif or .mp4 file name, or a directory")
    return [out]


def render_videos(policy_path: Path, targets: list[Path], seed: int, fixed: dict, log=print,
                  obj: str | None = None) -> list[dict]:
    """One deterministic episode per target on the first held-out ("test") placements, in order
    (on ``obj``, default the policy's first object)."""
    from forcegrasp.evaluation import placements
    from forcegrasp.video import episode_video

    policy = _load_policy(policy_path)
    env = _env_for(policy, policy_path, dict(fixed), obj)
    done = []
    try:
        for place, target in zip(placements(seed, len(targets), env.jitter, "test", clear=env.is_clear), targets):
            info, r = episode_video(env, policy, place, target)
            dx, dy = place.offset
            log(f"test placement {place.index} (offset {100 * dx:+.2f}, {100 * dy:+.2f} cm): "
                f"{'success' if r.success else f'failure ({r.failure})'}, return {r.ret:.1f}, {r.length} steps: "
                f"wrote {target} ({info.frames} frames, {info.width}x{info.height}, "
                f"{target.stat().st_size / 1e3:.0f} kB)")
            done.append({"placement": place.index, "path": str(target), "success": r.success, "return": r.ret})
    finally:
        env.close()
    return done


def _logger(folder: Path | None, env, placement, meta, policy_path: Path):
    """An MCAP episode log (``forcegrasp replay`` renders it), or None without ``--log-dir``."""
    if folder is None:
        return None
    from forcegrasp.mcap_log import EpisodeLogger

    folder.mkdir(parents=True, exist_ok=True)
    info = {"policy": str(policy_path), "object": env.object_spec.name, "episode": placement.index, "stream": "test"}
    return EpisodeLogger(folder / f"test-{placement.index:03d}.mcap", env, info)


def plot_rows(rows: list[dict], out: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    for obj in dict.fromkeys(r["object"] for r in rows):  # one line per object of a multi-object policy
        some = [r for r in rows if r["object"] == obj]
        ax.plot([r["value"] for r in some], [100 * r["success_rate"] for r in some], marker="o", label=obj)
    if len({r["object"] for r in rows}) > 1:
        ax.legend()
    ax.set(xlabel=rows[0]["setting"], ylabel="success rate (%)", ylim=(-3, 103), title=title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp eval", description=__doc__.splitlines()[0],
                                     epilog="e.g. forcegrasp eval runs/mug --sweep mass_scale=5,1,0.5 --env object_tolerance=0.03; "
                                     "forcegrasp eval mug-ff-s0 --video mug.gif")
    parser.add_argument("policy", type=Path, help="policy file, a run directory (its evaluator's best checkpoint), "
                        "or a shipped policy's name (e.g. mug-ff-s0)")
    parser.add_argument("--episodes", type=int, default=100, help="placements per setting (default 100)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the test placements (default 0)")
    parser.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                        help=f"fixed env setting, repeatable; KEY one of {', '.join(SWEEPABLE)}")
    parser.add_argument("--sweep", metavar="KEY=V1,V2,...", help="test at each value of one env setting")
    parser.add_argument("--object", action="append", default=[], metavar="NAME",
                        help="test only this one of a multi-object policy's objects (repeatable; default all)")
    parser.add_argument("--unseen", action="append", default=[], metavar="NAME",
                        help="also test on this object the policy was not trained on, zero-shot (repeatable)")
    parser.add_argument("--json", type=Path, help="write the rows as JSON")
    parser.add_argument("--plot", type=Path, help="PNG of success rate against the swept setting")
    parser.add_argument("--log-dir", type=Path, help="write each episode as an MCAP log here (forcegrasp replay renders it)")
    parser.add_argument("--video", type=Path, metavar="OUT.gif|OUT.mp4|DIR",
                        help="render instead of scoring: a .gif (320x240) or .mp4 (640x480), at a quarter speed, "
                        "of the episode on the first held-out placement, or in a directory test-000.gif... for "
                        "the first --video-count placements; with the --env settings, the object's camera")
    parser.add_argument("--video-count", type=int, default=4,
                        help="videos written into a --video directory (default 4)")
    parser.add_argument("--video-format", choices=("gif", "mp4"), default="gif",
                        help="format of the videos written into a --video directory (default gif)")
    args = parser.parse_args(argv)
    try:
        fixed = dict((k, v[0]) for k, v in (parse_setting(s, many=False) for s in args.env))
        sweep = parse_setting(args.sweep, many=True) if args.sweep else None
        if args.episodes < 1:
            raise ValueError("--episodes must be at least 1")
        if args.plot and not sweep:
            raise ValueError("--plot needs --sweep")
        if args.video and (sweep or args.plot or args.json or args.log_dir):
            raise ValueError("--video renders episodes and scores none: "
                             "leave out --sweep, --plot, --json and --log-dir")
        targets = video_targets(args.video, args.video_count, args.video_format) if args.video else None
        policy_path = resolve_policy(args.policy)
    except (ValueError, FileNotFoundError) as exc:
        parser.exit(2, f"forcegrasp eval: {exc}\n")
    if targets is not None:
        print(f"policy {policy_path}: rendering {len(targets)} held-out episode(s)", flush=True)
        try:
            render_videos(policy_path, targets, args.seed, fixed, log=lambda line: print(line, flush=True),
                          obj=args.object[0] if args.object else None)
        except ValueError as exc:
            parser.exit(2, f"forcegrasp eval: {exc}\n")
        return 0
    print(f"policy {policy_path}, {args.episodes} test placements per setting", flush=True)
    try:
        rows = evaluate_settings(policy_path, args.episodes, args.seed, fixed, sweep,
                                 log=lambda line: print(line, flush=True), log_dir=args.log_dir,
                                 objects=args.object or None, unseen=args.unseen)
    except ValueError as exc:
        parser.exit(2, f"forcegrasp eval: {exc}\n")
    print()
    many = len({r["object"] for r in rows}) > 1
    print(f"| {'object | ' if many else ''}{rows[0]['setting'] or 'settings'} | success | mean return | failures |")
    print(f"|{'---|' if many else ''}---|---:|---:|---|")
    for r in rows:
        name = r["object"] + (" (unseen)" if r["zero_shot"] else "")
        print(f"| {name + ' | ' if many else ''}{r['value'] if r['setting'] else 'as given'} | "
              f"{r['success_rate']:.0%} | {r['mean_return']:.1f} | "
              f"{', '.join(f'{k}: {n}' for k, n in sorted(r['failures'].items(), key=str)) or '-'} |")
    if many:
        for value in dict.fromkeys(r["value"] for r in rows):
            some = [r for r in rows if r["value"] == value and not r["zero_shot"]]
            print(f"| worst object | {value if rows[0]['setting'] else 'as given'} | "
                  f"{aggregate([r['success_rate'] for r in some]):.0%} | "
                  f"{aggregate([r['mean_return'] for r in some]):.1f} | - |")
    if args.json:
        args.json.write_text(json.dumps({"policy": str(policy_path), "rows": rows}, indent=1))
    if args.plot:
        r = rows[0]
        names = ", ".join(dict.fromkeys(x["object"] for x in rows))
        title = (f"{names}, force feedback {'on' if r['force_feedback'] else 'off'}: {policy_path.name}\n"
                 f"{r['episodes']} held-out placements per point")
        print(f"wrote {plot_rows(rows, args.plot, title)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
