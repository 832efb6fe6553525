"""``forcegrasp experiment``: one training configuration for a wall-clock budget, scored at fixed marks.

Runs the real cluster (`forcegrasp.cli.up.up`: learner, actors, evaluator as processes, exactly
what ``forcegrasp up`` runs) for ``--minutes`` of wall-clock. Every ``--mark-every`` minutes it
freezes two policy files into ``<run>/marks/``:

- ``best-MM``: the evaluator's current best (what ``forcegrasp best`` would hand a user then);
- ``latest-MM``: the learner's newest policy snapshot.

When training stops, each frozen file is tested on the same ``--episodes`` held-out placements
(the ``"test"`` stream of seed ``--test-seed``, never used to pick a checkpoint), deterministic
actions, on every core. The record, ``<run>/experiment.json`` (``"format": "forcegrasp-experiment"``,
``"version": 2``), holds the configuration, the settings the run trained with (``effective``), the
marks, their steps and scores; ``forcegrasp experiment --plot OUT.png RUN...`` overlays several
records (success against wall-clock minutes and against environment steps). A record of another
format or version is refused (`check_record`).

Resumable: the same command continues an interrupted experiment: training resumes from the
learner's checkpoint, wall-clock counts on from where it stopped, marks already taken are kept
and only untested files are evaluated. The clock is saved every `CLOCK_SAVE_S` seconds, not only
at marks, so a run killed outright (no chance to save) resumes at most that much early; training
done after the learner's last checkpoint is lost and its minutes stay counted, so a resumed run is
never given time. Each resume is listed in the record (``"resumed_at_s"``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from forcegrasp.cli.experiment_plot import plot_records  # noqa: F401  (forcegrasp experiment --plot)
from forcegrasp.report import FRESH_WORKERS
from forcegrasp.rundir import RunDir

RECORD = RunDir(".").experiment.name
#: What a record says it is, as its first two keys; readers refuse anything else (`check_record`).
RECORD_FORMAT = "forcegrasp-experiment"
RECORD_VERSION = 2
#: Seconds between saves of the wall-clock spent (a killed run resumes at most this early).
CLOCK_SAVE_S = 10.0


# ---------------------------------------------------------------------------------- the record
class RecordError(ValueError):
    """A file that is not an experiment record this ForceGrasp reads, with the reason in the message."""


def check_record(record, source) -> dict:
    """The record, if it is a `RECORD_FORMAT` record of `RECORD_VERSION`; else a `RecordError` naming
    ``source`` (the file) and the version found."""
    wanted = f"this ForceGrasp reads {RECORD_FORMAT!r} records of version {RECORD_VERSION}"
    if not isinstance(record, dict) or ("format" not in record and "version" not in record):
        raise RecordError(f"{source}: not a versioned experiment record (no 'format' and 'version' keys); {wanted}")
    if record.get("format") != RECORD_FORMAT:
        raise RecordError(f"{source}: format {record.get('format')!r} is not an experiment record; {wanted}")
    if record.get("version") != RECORD_VERSION:
        raise RecordError(f"{source}: experiment record version {record.get('version')!r} is not supported; {wanted}")
    return record


def read_record(path: Path) -> dict:
    """An experiment record file, checked (`check_record`); a `RecordError` for invalid JSON too."""
    try:
        record = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise RecordError(f"{path}: not JSON ({exc})") from None
    return check_record(record, path)


def load_record(run_dir: Path) -> dict | None:
    path = RunDir(run_dir).experiment
    return read_record(path) if path.is_file() else None


def save_record(run_dir: Path, record: dict) -> None:
    path = RunDir(run_dir).experiment
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(record, indent=1))
    os.replace(tmp, path)


def _current_files(run_dir: Path) -> dict[str, Path]:
    """The learner's latest snapshot and the evaluator's best right now."""
    out = {}
    latest = RunDir(run_dir).latest_policy
    if latest.is_file():
        out["latest"] = latest
    try:
        best = RunDir(run_dir).best_policy()
    except (OSError, ValueError):
        best = None
    if best is not None:
        out["best"] = best
    return out


def take_mark(run_dir: Path, record: dict, minute: float, elapsed_s: float) -> dict:
    """Freeze the current best and latest policy files as this mark's; the step recorded is the
    frozen copy's own (the live files are replaced atomically, so a copy is one whole file)."""
    from forcegrasp.policy_file import PolicyFileError, load_policy_file

    marks_dir = RunDir(run_dir).marks
    marks_dir.mkdir(exist_ok=True)
    mark = {"minute": minute, "elapsed_s": round(elapsed_s, 1), "files": {}, "steps": {}, "test": {}}
    for kind, path in _current_files(run_dir).items():
        dst = marks_dir / f"{kind}-{minute:05.1f}.safetensors"
        try:
            shutil.copyfile(path, dst)
            step = int(load_policy_file(dst)[1].training_steps)
        except (OSError, PolicyFileError):  # the evaluator replaced its best meanwhile: the next mark has it
            continue
        mark["files"][kind] = dst.name
        mark["steps"][kind] = step
    record["marks"] = [m for m in record["marks"] if m["minute"] != minute] + [mark]
    record["marks"].sort(key=lambda m: m["minute"])
    save_record(run_dir, record)
    return mark


# ---------------------------------------------------------------------------------- testing
def _test_chunk(args) -> list[dict]:
    """Worker: run one policy file on some held-out placements (deterministic actions)."""
    path, places, env_kwargs = args
    from forcegrasp.env import FunctionalGraspEnv
    from forcegrasp.evaluation import run_episode
    from forcegrasp.policy import Policy

    policy = Policy.load(path)
    env = FunctionalGraspEnv.for_policy(policy.metadata, **env_kwargs)
    return [{"success": r.success, "ret": r.ret, "failure": r.failure, "length": r.length}
            for r in (run_episode(env, policy, p) for p in places)]


def test_files(paths: list[Path], episodes: int, seed: int, env_kwargs: dict, workers: int, log=print) -> list[dict]:
    """Success rate and mean return of each policy file on the same held-out placements."""
    from forcegrasp.env import FunctionalGraspEnv
    from forcegrasp.evaluation import placements
    from forcegrasp.policy_file import load_policy_file

    results = []
    if not paths:
        return results
    meta = load_policy_file(paths[0])[1]
    probe = FunctionalGraspEnv.for_policy(meta, **env_kwargs)
    places = placements(seed, episodes, probe.jitter, "test", clear=probe.is_clear)
    chunks = max(1, workers)
    jobs = [(str(p), places[i::chunks], env_kwargs) for p in paths for i in range(chunks)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=max(1, workers), mp_context=FRESH_WORKERS) as pool:
        outs = list(pool.map(_test_chunk, jobs))
    for k, path in enumerate(paths):
        eps = [e for out in outs[k * chunks:(k + 1) * chunks] for e in out]
        n = len(eps)
        results.append({"episodes": n, "success_rate": sum(e["success"] for e in eps) / n,
                        "mean_return": sum(e["ret"] for e in eps) / n})
    log(f"tested {len(paths)} policy files on {episodes} held-out placements in {time.perf_counter() - t0:.0f} s")
    return results


def online_at(scalars: dict, step: int) -> dict | None:
    """The actors' online figures as the learner logged them at ``step`` or just before: their last
    100 episodes, sampled actions, weights changing under them (issue 15) -- what the progress
    line showed when the mark's latest snapshot was taken, to set beside its held-out test."""
    def last(tag: str) -> tuple[int, float] | None:  # the (step, value) logged at or before `step`
        steps, values = scalars.get(tag, ([], []))
        before = [(int(s), float(v)) for s, v in zip(steps, values) if s <= step]
        return before[-1] if before else None

    out = {}
    for key, tag in (("success_rate", "actors/success_rate_100"), ("return_mean", "actors/return_mean_100")):
        if (point := last(tag)) is None:
            return None
        out["step"], out[key] = point
    for key in ("mass_scale_min", "noise_std_max"):  # how far randomisation had opened (a curriculum's level)
        if (point := last(f"actors/{key}")) is not None:
            out[key] = point[1]
    return out


def add_online(run_dir: Path, record: dict) -> None:
    """Give every mark that has none the online figures at its latest snapshot's step."""
    todo = [m for m in record["marks"] if "online" not in m and "latest" in m["steps"]]
    tb = RunDir(run_dir).tensorboard
    if not todo or not tb.is_dir():
        return
    from forcegrasp.cli.plot import read_scalars

    scalars = read_scalars(tb)
    for m in todo:
        online = online_at(scalars, m["steps"]["latest"])
        if online is not None:
            m["online"] = online
    save_record(run_dir, record)


def test_marks(run_dir: Path, record: dict, workers: int, log=print) -> None:
    """Score every frozen file of every mark that has no score yet, then save the record. With test
    conditions (``record["conditions"]``) each file is tested under each one, on the same placements
    per condition, and its score is their mean (`forcegrasp.conditions.mix`); with several objects
    (``record["objects"]``) on each object, and the figures aggregate over objects as the run's
    evaluator ranked them (``record["object_aggregate"]``, `forcegrasp.multi_object`)."""
    from forcegrasp.conditions import ConditionScore, env_kwargs, mix
    from forcegrasp.multi_object import aggregate

    add_online(run_dir, record)
    todo = [(m, kind) for m in record["marks"] for kind in m["files"] if kind not in m["test"]]
    if not todo:
        return
    paths = [RunDir(run_dir).marks / m["files"][kind] for m, kind in todo]
    base = record.get("test_env", {})
    conditions, objects = record.get("conditions") or [None], record.get("objects") or [None]
    per = {(o, c): test_files(paths, record["episodes"], record["test_seed"],
                              {**(env_kwargs(c, base) if c else base), **({"object_name": o} if o else {})}, workers,
                              lambda msg, what=" ".join(x for x in (o, c) if x): log(f"{what}: {msg}" if what else msg))
           for o in objects for c in conditions}

    def score(o, i) -> dict:  # one file on one object: its conditions' mean
        if conditions == [None]:
            return per[(o, None)][i]
        parts = {c: per[(o, c)][i] for c in conditions}
        mixed = mix({c: ConditionScore(p["mean_return"], p["success_rate"], p["episodes"]) for c, p in parts.items()})
        return {"episodes": mixed.episodes, "success_rate": mixed.success_rate, "mean_return": mixed.score,
                "conditions": parts}

    how = record.get("object_aggregate", "min")
    for i, (m, kind) in enumerate(todo):
        if objects == [None]:
            m["test"][kind] = score(None, i)
            continue
        each = {o: score(o, i) for o in objects}
        m["test"][kind] = {"episodes": sum(e["episodes"] for e in each.values()),
                           **{k: aggregate([e[k] for e in each.values()], how) for k in ("success_rate", "mean_return")},
                           "objects": each}
    save_record(run_dir, record)


def summary_lines(record: dict) -> list[str]:
    under = (f"the mean over conditions {', '.join(record['conditions'])}" if record.get("conditions")
             else "the run's own env settings")
    if record.get("objects"):
        under += f", the {record.get('object_aggregate', 'min')} over objects {', '.join(record['objects'])}"
    lines = [f"{record['label']} (seed {record['seed']}): held-out success on {record['episodes']} placements, "
             f"{under}"]
    for m in record["marks"]:
        t = m["test"]
        cells = [f"{kind} {t[kind]['success_rate']:.0%} (step {m['steps'].get(kind)})"
                 + (" [" + ", ".join(f"{c} {p['success_rate']:.0%}" for c, p in t[kind]["conditions"].items()) + "]"
                    if "conditions" in t[kind] else "")
                 + (" [" + ", ".join(f"{o} {p['success_rate']:.0%}" for o, p in t[kind]["objects"].items()) + "]"
                    if "objects" in t[kind] else "")
                 for kind in ("best", "latest") if kind in t]
        if "online" in m:
            cells.append(f"online {m['online']['success_rate']:.0%} (actors' last 100 episodes)")
        lines.append(f"  {m['minute']:5.1f} min: " + ", ".join(cells))
    return lines


# ---------------------------------------------------------------------------------- running
def effective_settings(config) -> dict:
    """What the run trains with after its recipe's per-object defaults: every SAC setting and the
    demonstrations per env. The record keeps them because `config` holds only the overrides, and a
    later recipe may mean something else by the same overrides."""
    import dataclasses

    from forcegrasp.recipes import demo_episodes, sac_config

    return {"sac": dataclasses.asdict(sac_config(config)),
            "demo_episodes": demo_episodes(config.env.object, config.actor.demo_episodes)}


def run_experiment(config, minutes: float, mark_every: float, episodes: int, test_seed: int, label: str,
                   evaluator: bool = True, workers: int | None = None, log=print) -> dict:
    from forcegrasp.cli.up import up

    run_dir = RunDir.of(config).root
    run_dir.mkdir(parents=True, exist_ok=True)
    record = load_record(run_dir) or {
        "format": RECORD_FORMAT, "version": RECORD_VERSION,
        "label": label, "seed": config.run.seed, "object": config.env.object, "force_feedback": config.env.force_feedback, "minutes": minutes, "mark_every": mark_every,
        "episodes": episodes, "test_seed": test_seed, "elapsed_s": 0.0, "config": config.to_dict(),
        "effective": effective_settings(config), "marks": [],
        # the test conditions of the marks (forcegrasp.conditions): the evaluator's, so that marks
        # are scored on what the run selects for
        "conditions": list(config.evaluator.conditions),
        # a multi-object run's objects and how their figures combine, as its evaluator ranks them
        **({"objects": list(config.env.objects), "object_aggregate": config.evaluator.object_aggregate}
           if len(config.env.objects) > 1 else {}),
    }
    record["minutes"] = minutes  # a resumed experiment may be given a longer budget
    save_record(run_dir, record)
    done_s = float(record["elapsed_s"])
    remaining = minutes * 60.0 - done_s
    if remaining > 1.0:
        if done_s > 0.0:
            record.setdefault("resumed_at_s", []).append(done_s)
            save_record(run_dir, record)
            log(f"experiment {label}: resuming at {done_s / 60:.1f} min of wall-clock from the learner's last checkpoint")
        log(f"experiment {label}: {remaining / 60:.1f} of {minutes} min to train; marks every {mark_every} min")
        t0 = time.monotonic()
        stop = threading.Event()
        taken = {m["minute"] for m in record["marks"]}

        def elapsed() -> float:
            return done_s + time.monotonic() - t0

        def save_clock() -> None:
            record["elapsed_s"] = round(elapsed(), 1)
            save_record(run_dir, record)

        def marker() -> None:
            """Take each mark on time; between marks, save the clock every CLOCK_SAVE_S seconds."""
            k = 1
            while not stop.is_set():
                minute = round(k * mark_every, 3)
                if minute >= minutes:
                    minute = float("inf")  # the final mark is taken after the cluster stops
                while minute not in taken and (wait := minute * 60.0 - elapsed()) > 0:
                    if stop.wait(min(wait, CLOCK_SAVE_S)):
                        return
                    save_clock()
                if minute not in taken:
                    record["elapsed_s"] = round(elapsed(), 1)
                    take_mark(run_dir, record, minute, record["elapsed_s"])  # saves the record, clock included
                k += 1

        thread = threading.Thread(target=marker, daemon=True, name="marks")
        thread.start()
        try:
            status = up(config, RunDir(run_dir).cluster_config, stop_after=remaining, log=log, evaluator=evaluator)
        finally:
            stop.set()
            thread.join()
            save_clock()
        if status:  # a service kept crashing (or the output closed): the marks would not mean what they say
            raise SystemExit(f"experiment {label}: the cluster stopped early (exit {status}); the record is kept "
                             "and the same command resumes it")
        if record["elapsed_s"] >= minutes * 60.0 - 1.0:
            take_mark(run_dir, record, float(minutes), record["elapsed_s"])
    test_marks(run_dir, record, workers or max(1, os.cpu_count() or 1), log)
    for line in summary_lines(record):
        log(line)
    return record


def main(argv=None) -> int:
    from forcegrasp.config import add_config_arguments, config_from_args

    parser = argparse.ArgumentParser(prog="forcegrasp experiment", description=__doc__.splitlines()[0])
    add_config_arguments(parser)
    parser.add_argument("--minutes", type=float, default=60.0, help="wall-clock budget of the training run")
    parser.add_argument("--mark-every", type=float, default=5.0, help="minutes between frozen policies")
    parser.add_argument("--episodes", type=int, default=50, help="held-out placements per frozen policy")
    parser.add_argument("--test-seed", type=int, default=0, help="seed of the held-out placement stream")
    parser.add_argument("--label", default=None, help="name of the configuration in plots (default: run name)")
    parser.add_argument("--no-evaluator", action="store_true", help="train without the evaluator (no 'best')")
    parser.add_argument("--workers", type=int, default=None, help="processes for testing (default: all cores)")
    parser.add_argument("--plot", metavar="OUT.png", default=None,
                        help="only plot: overlay the records of the run folders given as arguments")
    parser.add_argument("runs", nargs="*", help="with --plot: run folders (or experiment.json files)")
    args = parser.parse_args(argv)
    if args.plot:
        try:
            records = [read_record(p if p.is_file() else p / RECORD) for p in map(Path, args.runs)]
        except RecordError as exc:
            parser.error(str(exc))
        print(f"wrote {plot_records(records, Path(args.plot))}")
        return 0
    config = config_from_args(args)
    try:
        run_experiment(config, args.minutes, args.mark_every, args.episodes, args.test_seed,
                       args.label or config.run.name, evaluator=not args.no_evaluator, workers=args.workers,
                       log=lambda m: print(m, flush=True))
    except RecordError as exc:  # the run folder holds a record this version does not resume
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
