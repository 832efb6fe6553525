"""Evaluator service: the evaluator role (:class:`forcegrasp.ranking.Ranker`: score snapshots, keep
the top k, re-rank newcomers, log episodes to MCAP) wired to the learner's announcements, with the
best policy served as a Zenoh queryable and over read-only HTTP.

- Checkpoints are found two ways: announcements on ``forcegrasp/<run>/checkpoints`` and a scan
  of ``<output_dir>/<run>/checkpoints/`` at start and every ``--scan-every`` seconds, so a
  restarted evaluator or a missed message loses nothing. Announced paths are only hints: files
  are read from this run's own checkpoints folder, by their ``policy-<step>.safetensors`` name.
- A checkpoint is evaluated if it is at least ``evaluator.eval_every`` learner steps after the
  last one evaluated; the service takes the newest such (it follows training's front and skips
  what it cannot keep up with), ``--once`` every one, oldest first; ``evaluator.eval_episodes`` deterministic episodes on
  placements fixed by ``run.seed``; the score is the mean return (success rate recorded too).
- Top k (``evaluator.top_k``) in ``<output_dir>/<run>/evaluator/top/`` (see ``topk.py`` for the
  crash-safety rules); a newcomer is scored on ``evaluator.final_rank_episodes`` ranking
  placements and the best member by that score is marked in the index and served.
- Episodes go to ``<output_dir>/<run>/evaluator/episodes/<step>/{eval,rank}[-<object>][-<condition>]-<i>.mcap``
  (the object in a run of several, ``env.objects``; the test condition, ``evaluator.conditions``).
- Stats on ``forcegrasp/<run>/stats/evaluator/<id>``, liveliness token, SIGINT/SIGTERM stop it.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import queue
import signal
import threading
import time

from forcegrasp.config import Config, add_config_arguments, config_from_args
from forcegrasp.protocol import Keys, ProtocolError, RejectCounter, Stats, decode_checkpoint, encode_stats
from forcegrasp.protocol.best import BestPolicy
from forcegrasp.ranking import Ranker, ScoreFn
from forcegrasp.rundir import step_of
from forcegrasp_evaluator.endpoint import EvaluatorHTTPServer, Snapshot, declare_best_queryable

log = logging.getLogger("forcegrasp.evaluator")

class EvaluatorService(Ranker):
    """The evaluator role plus announcements, the best-policy endpoints, stats and TensorBoard."""

    def __init__(self, config: Config, instance: str = "0", *, score_fn: ScoreFn | None = None,
                 log_episodes: bool = True, scan_every: float = 10.0, stats_every: float = 2.0,
                 mcap_backend: str = "auto", newest_first: bool = True):
        super().__init__(config, score_fn=score_fn, log_episodes=log_episodes, mcap_backend=mcap_backend,
                         newest_first=newest_first)
        self.instance = instance
        self.keys = Keys(config.run.name)
        self.top.crash_hook = _crash_hook_from_env()
        self.scan_every = scan_every
        self.stats_every = stats_every
        self.rejects = RejectCounter()
        self.announcements: queue.Queue = queue.Queue(maxsize=4096)
        self.snapshot = Snapshot.build(config.run.name, None, self.top.to_json(with_history=False))
        self.http: EvaluatorHTTPServer | None = None
        self._t0 = self._last_scan = time.monotonic()
        self.writer = None  # TensorBoard, opened by run(): the evaluator's figures beside the learner's
        self.cpu: CpuBudget | None = None  # its CPU budget, while run() runs

    def on_commit(self, step, result) -> None:
        self.refresh_snapshot()
        if step is not None:
            if self.writer is not None:
                self.write_scalars(self.writer, step, result)

    def load(self) -> None:
        self._last_scan = time.monotonic()
        super().load()

    def on_announcement(self, payload: bytes) -> None:
        """Zenoh callback: only a queue put (decoding happens in the service loop)."""
        try:
            self.announcements.put_nowait(payload)
        except queue.Full:
            self.rejects.reject("queue_full")

    def _drain_announcements(self) -> None:
        while True:
            try:
                payload = self.announcements.get_nowait()
            except queue.Empty:
                return
            try:
                ckpt = decode_checkpoint(payload)
                name = os.path.basename(ckpt.path)
                step = step_of(name)
                if step is None:
                    raise ProtocolError("bad_field", f"path {ckpt.path!r} is not a policy-<step>.safetensors file")
                if step != ckpt.step:
                    raise ProtocolError("bad_field", f"path says step {step}, message says {ckpt.step}")
            except ProtocolError as exc:
                if self.rejects.reject(exc) <= 5:
                    log.warning("dropped a checkpoint announcement: %s", exc)
                continue
            self.rejects.accept()
            if not self._wanted(step) or step in self.pending:
                continue
            # The learner's path may be on another machine: the file is read from our own folder.
            path = self.checkpoint_dir / name
            if path.is_file():
                self.pending[step] = path
            else:
                self.counters.missing_files += 1
                log.warning("announced checkpoint %s is not in %s (does this evaluator share the learner's "
                            "output_dir?); the next scan will pick it up if it appears", name, self.checkpoint_dir)

    def poll_once(self) -> bool:
        """One turn of the service loop: take announcements, scan, evaluate the next checkpoint.
        Returns whether a checkpoint was processed."""
        self._drain_announcements()
        # Scan before every evaluation, not only every scan_every seconds: an announcement can
        # overtake older checkpoints this evaluator missed (it connected late, say), and those
        # must be evaluated first or the spacing rule would skip them for good.
        if self.pending or time.monotonic() - self._last_scan >= self.scan_every:
            self.scan()
            self._last_scan = time.monotonic()
        return self.evaluate_next()

    # ------------------------------------------------------------------ serving
    def refresh_snapshot(self) -> None:
        """Rebuild what the endpoints serve from the top k (after each commit)."""
        best_member = self.top.best
        best = None
        if best_member is not None:
            data = self.top.read_policy(best_member)
            best = BestPolicy(
                run=self.config.run.name, step=best_member.step, score=best_member.rank_score,
                success_rate=best_member.rank_success_rate, episodes=best_member.rank_episodes,
                eval_score=best_member.score, eval_success_rate=best_member.success_rate,
                eval_episodes=best_member.episodes, object=best_member.object,
                force_feedback=best_member.force_feedback, policy_version=best_member.policy_version,
                sha256=best_member.sha256, policy=data, time=time.time())
        self.snapshot = Snapshot.build(self.config.run.name, best, self.top.to_json(with_history=False))

    def _on_query(self, outcome: str) -> None:
        self.counters.queries += 1
        if outcome != "ok":
            self.counters.bad_queries += 1

    def stats(self) -> dict:
        c = self.counters
        return {
            **super().stats(),
            "queries": c.queries,
            "bad_queries": c.bad_queries,
            "http_port": self.http.port if self.http is not None else None,
            "http_requests": dict(self.http.requests_by_status) if self.http is not None else {},
            "rejected": self.rejects.total,
            "rejected_by_reason": self.rejects.counts(),
            "uptime_s": time.monotonic() - self._t0,
            "cpu_share": self.cpu.share() if self.cpu is not None else None,
        }

    def start_http(self) -> None:
        ev = self.config.evaluator
        try:
            self.http = EvaluatorHTTPServer(ev.http_host, ev.http_port, lambda: self.snapshot).start()
            log.info("HTTP: http://%s:%d/best (metadata), /best/policy (download), /top", ev.http_host, self.http.port)
        except OSError as exc:  # the Zenoh endpoint still works; say so loudly instead of dying
            log.error("HTTP server not started on %s:%d: %s (the Zenoh endpoint still serves %s)",
                      ev.http_host, ev.http_port, exc, self.keys.best)

    # ------------------------------------------------------------------ service loop
    def run(self, stop: threading.Event) -> None:
        from forcegrasp.runtime import open_service_session
        from forcegrasp.transport import close_session, declare_publisher, declare_token

        from torch.utils.tensorboard import SummaryWriter

        self._stop = stop
        self.load()
        self.start_http()
        self.writer = SummaryWriter(str(self.files.tensorboard), filename_suffix=".evaluator")
        session = open_service_session(self.config, "evaluator")
        stats_thread = None
        try:
            token = declare_token(session, self.keys.alive("evaluator", self.instance))
            subscriber = session.declare_subscriber(self.keys.checkpoints,
                                                    lambda s: self.on_announcement(s.payload.to_bytes()))
            queryable = declare_best_queryable(session, self.config.run.name, lambda: self.snapshot, self._on_query)
            stats_pub = declare_publisher(session, self.keys.stats("evaluator", self.instance))

            def publish_stats() -> None:
                while not stop.wait(self.stats_every):
                    try:
                        stats_pub.put(encode_stats(Stats("evaluator", self.instance, self.stats())))
                    except Exception:
                        log.exception("publishing stats failed")

            stats_pub.put(encode_stats(Stats("evaluator", self.instance, self.stats())))
            stats_thread = threading.Thread(target=publish_stats, name="evaluator-stats", daemon=True)
            stats_thread.start()
            budget = CpuBudget(self.config.evaluator.cpu_share)
            self.cpu = budget
            while not stop.is_set():
                if not self.poll_once():
                    stop.wait(0.1)
                elif (rest := budget.rest()) > 0:
                    stop.wait(rest)  # within its CPU share: training keeps the cores it needs
            subscriber.undeclare()
            queryable.undeclare()
            token.undeclare()
        finally:
            stop.set()
            if stats_thread is not None:
                stats_thread.join(timeout=5)
            close_session(session)
            self.writer.close()
            if self.http is not None:
                self.http.stop()


class CpuBudget:
    """Keeps a process's CPU time within ``limit`` of one core, averaged since it was made: after
    each piece of work, `rest` says how long to pause. Scoring several test conditions costs
    several times the episodes; on a small machine an unbounded evaluator takes the cores training
    needs, so its share is a setting (``evaluator.cpu_share``) and its measured share a statistic."""

    def __init__(self, limit: float, clock=time.monotonic, cpu_clock=time.process_time):
        self.limit, self.clock, self.cpu_clock = float(limit), clock, cpu_clock
        self.wall0, self.cpu0 = clock(), cpu_clock()

    def share(self) -> float:
        """CPU seconds used per wall-clock second so far."""
        wall = self.clock() - self.wall0
        return (self.cpu_clock() - self.cpu0) / wall if wall > 0 else 0.0

    def rest(self) -> float:
        """Seconds to pause so that the share falls back to the limit (0 when within it)."""
        if self.limit >= 1.0:
            return 0.0
        return max(0.0, (self.cpu_clock() - self.cpu0) / self.limit - (self.clock() - self.wall0))


CRASH_ENV = "FORCEGRASP_FAULT_CRASH_AT"  # not FORCEGRASP_EVALUATOR_*: that prefix is configuration


def _crash_hook_from_env():
    """Fault injection for the crash tests: ``FORCEGRASP_FAULT_CRASH_AT=policy_written:3``
    SIGKILLs this process the 3rd time it passes that point (``policy_written``: a new member's
    file is on disk, its index not yet; ``index_written``: the index is, evicted files remain)."""
    spec = os.environ.get(CRASH_ENV)
    if not spec:
        return None
    point, _, count = spec.partition(":")
    remaining = {"n": int(count or 1)}

    def hook(name: str) -> None:
        if name == point:
            remaining["n"] -= 1
            if remaining["n"] <= 0:
                log.warning("%s=%s: killing myself now", CRASH_ENV, spec)
                os.kill(os.getpid(), signal.SIGKILL)

    return hook


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp evaluator", description=__doc__.splitlines()[0])
    parser.add_argument("--id", default="0", help="instance id in the stats and liveliness keys (default 0)")
    parser.add_argument("--scan-every", type=float, default=10.0, metavar="S",
                        help="seconds between scans of the checkpoints folder (default 10)")
    parser.add_argument("--stats-every", type=float, default=2.0, metavar="S", help="seconds between stats messages")
    parser.add_argument("--no-mcap", action="store_true", help="do not write MCAP episode logs")
    parser.add_argument("--mcap-backend", choices=("auto", "sdk", "mcap"), default="auto",
                        help="MCAP writer: foxglove-sdk, the pure-Python mcap package, or auto (sdk if installed)")
    parser.add_argument("--all", action="store_true",
                        help="evaluate every checkpoint eval_every apart, oldest first, even when behind training "
                             "(default: follow training's front, skipping the backlog)")
    parser.add_argument("--once", action="store_true",
                        help="evaluate the checkpoints already on disk (re-scoring the top k if the protocol changed), "
                             "print the top k and exit; no network (e.g. to score a finished run)")
    add_config_arguments(parser)
    args = parser.parse_args(argv)
    config = config_from_args(args)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    from forcegrasp.policy import configure_threads
    from forcegrasp.runtime import stop_on_signals

    configure_threads(1)  # one observation at a time: more threads only contend with the physics
    stop = stop_on_signals()
    service = EvaluatorService(config, args.id, log_episodes=not args.no_mcap, scan_every=args.scan_every,
                               stats_every=args.stats_every, mcap_backend=args.mcap_backend,
                               newest_first=not (args.once or args.all))
    ev = config.evaluator
    log.info("evaluator %s: run %s, %s, every %d steps on %d episodes, top %d ranked on %d episodes, checkpoints in %s",
             args.id, config.run.name, ", ".join(service.objects), ev.eval_every, ev.eval_episodes, ev.top_k,
             ev.final_rank_episodes, service.checkpoint_dir)
    try:
        if args.once:
            service._stop = stop
            service.load()
            while not stop.is_set() and service.poll_once():
                pass
            print(json.dumps(service.top.to_json(with_history=False), indent=1))
        else:
            service.run(stop)
    finally:
        service.close()
    log.info("evaluator %s: stopped after %d evaluations", args.id, service.counters.evaluations)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
