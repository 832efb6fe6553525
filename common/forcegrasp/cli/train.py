"""``forcegrasp train``: the whole training service in one process, no network.

The same roles ``forcegrasp up`` distributes, wired directly: one actor
(:class:`forcegrasp.acting.Actor`, ``actor.envs_per_actor`` envs) hands its batches to the learner
(:class:`forcegrasp.learning.Learner`, the configured recipe and update-to-data ratio), which hands
it new weights every ``learner.broadcast_every`` updates; the evaluator's scoring
(:class:`forcegrasp.ranking.Ranker`) follows the snapshots in a thread, as the evaluator service
would. Same configuration (``--config``/``--set``), same run directory, same files, so a run
trained here and one trained by ``forcegrasp up`` are read, plotted, served and resumed the same
way. Interrupt it and run the same command again: it resumes from the last checkpoint.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

from forcegrasp.config import ConfigError, add_config_arguments, config_from_args
from forcegrasp.objects import ObjectFileError, load_object

MAX_UPDATES_PER_STEP = 64  # the actor waits for the learner, as actors wait on a learner's headroom


def build_config(args):
    overrides = list(args.overrides)
    if args.object:
        overrides.insert(0, f"env.object={args.object}")
    if args.run_dir:
        run_dir = Path(args.run_dir).resolve()
        overrides[:0] = [f"run.name={run_dir.name}", f"run.output_dir={run_dir.parent}"]
    if args.no_force_feedback:
        overrides.append("env.force_feedback=false")
    if args.seed is not None:
        overrides.append(f"run.seed={args.seed}")
    args.overrides = overrides
    return config_from_args(args)


class Evaluation(threading.Thread):
    """The evaluator role beside training: newest snapshot first, like the service."""

    def __init__(self, config, writer):
        super().__init__(name="evaluation", daemon=True)
        from forcegrasp.ranking import Ranker

        self.writer = writer
        self.stop = threading.Event()
        self.ranker = Ranker(config)
        self.ranker._stop = self.stop
        self.ranker.on_commit = self._scalars

    def _scalars(self, step, result) -> None:
        if step is not None:
            self.ranker.write_scalars(self.writer, step, result)

    def run(self) -> None:
        self.ranker.load()
        while not self.stop.is_set():
            self.ranker.scan()
            if not self.ranker.evaluate_next():
                self.stop.wait(0.5)

    def summary(self) -> str:
        from forcegrasp.cli.up import evaluator_summary

        return evaluator_summary(self.ranker.stats())


def train(config, steps: int, evaluate: bool = True, log=print) -> Path:
    """Train until ``steps`` transitions are in; returns the run directory."""
    from torch.utils.tensorboard import SummaryWriter

    from forcegrasp.acting import Actor
    from forcegrasp.learning import Learner
    learner = Learner(config)
    if learner.resumed:
        log(f"resumed {learner.files.root} at step {learner.ingested} ({len(learner.buffer)} transitions in replay)")
    actor = Actor(config, "local", seed=config.run.seed + 1000)
    writer = SummaryWriter(str(learner.files.tensorboard))
    learner.on_episode = lambda r, s, step: (writer.add_scalar("actors/episode_return", r, step),
                                             writer.add_scalar("actors/success", float(s), step))
    evaluation = Evaluation(config, writer) if evaluate else None
    if evaluation is not None:
        evaluation.start()

    def give_weights() -> None:
        w = learner.weights()
        actor.update(w.params, learner.metadata(), w.policy_version)

    give_weights()
    t0 = last_stats = time.monotonic()
    updates0, ingested0, last_broadcast, metrics = learner.sac.num_updates, learner.ingested, learner.sac.num_updates, {}
    try:
        while learner.ingested < steps:
            batch = actor.step()
            if batch is None:
                continue
            learner.observe(batch)
            while learner.updates_due >= 1:
                metrics = learner.train(MAX_UPDATES_PER_STEP) or metrics
            if learner.sac.num_updates - last_broadcast >= config.learner.broadcast_every:
                give_weights()
                last_broadcast = learner.sac.num_updates
            learner.save_due()
            now = time.monotonic()
            if now - last_stats >= config.learner.stats_every_s or learner.ingested >= steps:
                values = learner.stats(now - t0, updates0, ingested0)
                t0, updates0, ingested0, last_stats = now, learner.sac.num_updates, learner.ingested, now
                learner.write_scalars(writer, values, metrics)
                writer.flush()
                ret = "-" if values["return_mean"] is None else f"{values['return_mean']:.1f}"
                succ = "-" if values["success_rate"] is None else f"{values['success_rate']:.0%}"
                log(f"step {learner.ingested:>8}/{steps}  {values['ingest_per_s']:6.1f} steps/s  updates "
                    f"{learner.sac.num_updates}  online return(100) {ret}  online success(100) {succ}"
                    + (f"  | {evaluation.summary()}" if evaluation is not None else ""))
    finally:
        learner.checkpoint()
        if evaluation is not None:
            evaluation.stop.set()
            evaluation.join(timeout=600)
            if learner.ingested >= steps:  # the final snapshot is scored before the command returns
                evaluation.stop.clear()
                evaluation.ranker.scan()
                evaluation.ranker.evaluate_next()
                log(evaluation.summary())
            evaluation.ranker.close()
        writer.close()
        actor.close()
    return learner.files.root


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp train", description=__doc__.splitlines()[0])
    parser.add_argument("object", nargs="?", default=None, help="object name (default: env.object of the configuration)")
    parser.add_argument("--steps", type=int, default=1_000_000, help="total environment steps (paper: 1M)")
    parser.add_argument("--run-dir", default=None,
                        help="run directory (default: run.output_dir/run.name); an existing run resumes")
    parser.add_argument("--no-force-feedback", action="store_true", help="the paper's ablation: no joint torques")
    parser.add_argument("--seed", type=int, default=None, help="run.seed")
    parser.add_argument("--no-eval", action="store_true", help="no evaluator beside training")
    add_config_arguments(parser)
    args = parser.parse_args(argv)
    try:
        config = build_config(args)
        load_object(config.env.object)
    except (ConfigError, ObjectFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        root = train(config, args.steps, evaluate=not args.no_eval, log=lambda m: print(m, flush=True))
    except KeyboardInterrupt:
        print("interrupted: checkpoint written; the same command resumes")
        return 130
    print(f"done: {root}; best policy: forcegrasp eval {root}; curves: forcegrasp plot {root}")
    return 0
