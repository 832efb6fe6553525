"""The evaluator role: score the learner's policy snapshots the paper's way and keep the best.

Each snapshot ``evaluator.eval_every`` steps after the last one scored is played on
``evaluator.eval_episodes`` fixed placements (deterministic actions; the score is the mean
return, the success rate is recorded too). A snapshot good enough for the top k
(``evaluator.top_k``, kept on disk by :mod:`forcegrasp.topk`) is scored again on
``evaluator.final_rank_episodes`` ranking placements, and the best member by that score is the
policy a user gets. Placements are fixed by ``run.seed``; episodes can be logged to MCAP under
``<run>/evaluator/episodes/<step>/``. A run of several objects (``env.objects``) scores each object
under each test condition and ranks on ``evaluator.object_aggregate`` over the objects
(`forcegrasp.multi_object`); its logs are ``eval-<object>-<i>.mcap``.

No network: the evaluator service adds announcements, serving and stats;
``forcegrasp train`` runs the same role in its own process.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import json
import logging
import os
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from forcegrasp.config import Config
from forcegrasp.evaluation import EvalResult, Interrupted, Placement, evaluate, placements
from forcegrasp.multi_object import check_objects, run_objects, score_grid
from forcegrasp.policy_file import PolicyFileError, PolicyMetadata, load_policy_bytes, policy_to_bytes
from forcegrasp.rundir import RunDir, policy_file_name, step_of
from forcegrasp.task import check_policy
from forcegrasp.topk import MAX_POLICY_BYTES, Member, TopK, sha256

log = logging.getLogger("forcegrasp.evaluator")

#: ``score_fn(policy, weights, metadata, placements, kind, step, condition=None) -> EvalResult``; kind is
#: "eval" or "rank", condition a `forcegrasp.conditions` name or None (the run's own env); a run of
#: several objects passes the object too (keyword ``object``).
ScoreFn = Callable[..., EvalResult]


class CheckpointRejected(Exception):
    """A checkpoint file that cannot be evaluated (corrupt, other task, other architecture)."""


@dataclass
class Counters:
    evaluations: int = 0
    rank_evaluations: int = 0
    episodes: int = 0
    episode_seconds: float = 0.0
    entered_top: int = 0
    skipped: int = 0
    bad_checkpoints: int = 0
    missing_files: int = 0
    queries: int = 0
    bad_queries: int = 0
    pruned_logs: int = 0


class Ranker:
    """Finds snapshots in the run's checkpoints folder, scores them, keeps the top k."""

    def __init__(self, config: Config, *, score_fn: ScoreFn | None = None, log_episodes: bool = True,
                 mcap_backend: str = "auto", newest_first: bool = True):
        self.config = config
        self.newest_first = newest_first
        self.files = RunDir.of(config)
        self.run_dir = self.files.root
        self.checkpoint_dir = self.files.checkpoints
        self.dir = self.files.evaluator
        self.episodes_dir = self.files.episodes
        self.dir.mkdir(parents=True, exist_ok=True)
        self._lock_file = self._take_lock()
        ev = config.evaluator
        # Test conditions (forcegrasp.conditions), each with its own env and placements; None is
        # the run's own env settings, the one condition when evaluator.conditions is empty.
        self.conditions: list[str | None] = list(ev.conditions) or [None]
        self.objects = run_objects(config.env)  # each with its envs and placements: keys (object, condition)
        self.object_keys: list[str | None] = self.objects if len(self.objects) > 1 else [None]
        self.envs: dict = {}
        self.eval_places, self.rank_places = {}, {}
        for key in ((o, c) for o in self.object_keys for c in self.conditions):
            env = self._ensure_env(key[1], key[0])
            self.eval_places[key] = placements(config.run.seed, ev.eval_episodes, env.jitter, "eval", env.is_clear)
            self.rank_places[key] = placements(config.run.seed, ev.final_rank_episodes, env.jitter, "rank",
                                               env.is_clear)
        self.top = TopK(self.files.top, ev.top_k, run=config.run.name)
        self.log_episodes = log_episodes
        self.mcap_backend = mcap_backend
        self._score_fn = score_fn or self._rollouts
        self.counters = Counters()
        self.pending: dict[int, Path] = {}
        self.failed: set[int] = set()
        self.current: int | None = None
        self._stop = threading.Event()
        self.last_result: tuple[int, EvalResult] | None = None

    def _take_lock(self):
        """One evaluator per run folder: a second one would interleave writes to the same top k.
        ``flock`` is released by the kernel when the process dies, even by SIGKILL."""
        f = open(self.dir / "lock", "a+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.close()
            raise SystemExit(f"error: another evaluator is running for run {self.config.run.name!r} "
                             f"(it holds {self.dir / 'lock'})") from None
        f.seek(0)
        f.truncate()
        f.write(f"{os.getpid()}\n")
        f.flush()
        return f

    def close(self) -> None:
        """Release the run's evaluator lock (also released by the kernel when the process dies)."""
        if self._lock_file is not None and not self._lock_file.closed:
            self._lock_file.close()
        for env in self.envs.values():
            env.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def protocol(self) -> dict:
        """What a score depends on besides the policy: a change invalidates stored scores."""
        e, ev = self.config.env, self.config.evaluator
        return {"object": e.object, "force_feedback": e.force_feedback, "mass_scale": e.mass_scale,
                "jitter": e.jitter, "torque_noise_std": e.torque_noise_std, "max_steps": e.max_steps,
                **e.action_steps(),
                **({"torque_history": e.torque_history} if e.torque_history else {}),
                **({"proprioception": e.proprioception} if e.proprioception != "measured" else {}),
                "seed": self.config.run.seed, "eval_episodes": ev.eval_episodes,
                "final_rank_episodes": ev.final_rank_episodes,
                **({"conditions": list(ev.conditions)} if ev.conditions else {}),
                **({"objects": self.objects, "object_aggregate": ev.object_aggregate} if self.object_keys[0] else {}),
                # the placements themselves: a change in how they are drawn (e.g. which offsets
                # are clear of the hand) invalidates scores as surely as a changed setting
                "placements": hashlib.sha256(json.dumps(
                    [[p.seed, *p.offset] for k in self.eval_places for p in self.eval_places[k] + self.rank_places[k]]
                ).encode()).hexdigest()[:16]}

    def load(self) -> None:
        """Reload the top k (verifying every file), re-score it if the protocol changed, scan."""
        if self.top.load(self.protocol()):
            log.warning("evaluation settings changed since the top k was scored: re-scoring its %d members",
                        len(self.top.members))
            self._rescore_members()
        self.on_commit(None, None)
        best = self.top.best
        self._last_scan = time.monotonic()
        log.info("top %d: %d members, best %s, last evaluated step %s", self.top.k, len(self.top.members),
                 f"{best.file} ({best.rank_score:.2f})" if best else "none", self.top.last_step)
        self.scan()

    # ------------------------------------------------------------------ finding checkpoints
    def scan(self) -> int:
        """Add every ``policy-<step>.safetensors`` of the checkpoints folder not evaluated yet."""
        found = 0
        try:
            entries = list(os.scandir(self.checkpoint_dir))
        except FileNotFoundError:
            return 0
        for entry in entries:
            step = step_of(entry.name)
            if step is not None and self._wanted(step) and step not in self.pending:
                self.pending[step] = Path(entry.path)
                found += 1
        return found

    def _wanted(self, step: int) -> bool:
        last = self.top.last_step
        return step not in self.failed and (last is None or step >= last + self.config.evaluator.eval_every)

    def next_checkpoint(self) -> tuple[int, Path] | None:
        """The next pending checkpoint far enough after the last evaluated one.

        Newest first (the service): an evaluator slower than training follows its front and skips
        what it cannot keep up with, instead of working through a growing backlog of stale
        checkpoints while it serves an old best. Oldest first (``--once``, scoring a finished
        run): every checkpoint ``eval_every`` apart is evaluated.
        """
        order = sorted(self.pending, reverse=self.newest_first)
        chosen = None
        for step in order:
            if chosen is not None and self.newest_first:
                del self.pending[step]  # older than the one chosen: it would never be wanted
                self.counters.skipped += 1
                continue
            if chosen is not None:
                break
            path = self.pending.pop(step)
            if self._wanted(step):
                chosen = (step, path)
            else:
                self.counters.skipped += 1
        return chosen

    # ------------------------------------------------------------------ evaluating
    def _ensure_env(self, condition: str | None = None, obj: str | None = None):
        """The env of a test condition (None: the run's own settings) and object (None: the run's
        one object), built once."""
        if (obj, condition) not in self.envs:
            from forcegrasp.conditions import env_kwargs
            from forcegrasp.runtime import make_env

            self.envs[obj, condition] = make_env(self.config, obj, **(env_kwargs(condition) if condition else {}))
        return self.envs[obj, condition]

    def _score(self, policy, weights, meta: PolicyMetadata, kind: str, step: int) -> EvalResult:
        """Score under every test condition, on every object: several conditions mix by their plain
        mean (``conditions``), several objects by ``evaluator.object_aggregate`` (``objects``)."""
        places = self.eval_places if kind == "eval" else self.rank_places

        def one(obj, c):
            kw = {"condition": c} if obj is None else {"condition": c, "object": obj}
            return self._score_fn(policy, weights, meta, places[obj, c], kind, step, **kw)

        return score_grid(one, self.object_keys, self.conditions, self.config.evaluator.object_aggregate)

    def _rollouts(self, policy, weights, meta: PolicyMetadata, places: list[Placement], kind: str,
                  step: int, condition: str | None = None, object: str | None = None) -> EvalResult:  # noqa: A002
        env = self._ensure_env(condition, object)
        prefix = "-".join(x for x in (kind, object, condition) if x)
        log_dir = None
        if self.log_episodes:
            log_dir = self.episodes_dir / f"{step:09d}"
            log_dir.mkdir(parents=True, exist_ok=True)
            for leftover in log_dir.glob(f".{prefix}-*.tmp"):
                leftover.unlink(missing_ok=True)
        meta_fields = {"run": self.config.run.name, "checkpoint_step": step, "policy_version":
                       meta.extra.get("policy_version", 0), "checkpoint": policy_file_name(step),
                       "condition": condition or "run", "object": object or self.config.env.object}

        def counted(_result) -> None:
            self.counters.episodes += 1

        return evaluate(env, policy, places, log_dir=log_dir, log_prefix=prefix, log_metadata=meta_fields,
                        should_stop=self._stop.is_set, on_episode=counted, logger_backend=self.mcap_backend)

    def _check(self, data: bytes, source: str):
        """Parse and check a checkpoint against this run's task; returns (weights, metadata)."""
        try:
            weights, meta = load_policy_bytes(data, source=source)
        except PolicyFileError as exc:
            raise CheckpointRejected(str(exc)) from None
        env = self.config.env
        try:
            check_policy(meta, env.object, env.force_feedback, env.action_steps(), env.torque_history, env.proprioception)
            check_objects(meta, self.objects)
        except ValueError as exc:
            raise CheckpointRejected(f"{source}: {exc} (this run: {env.object}, force_feedback={env.force_feedback}, "
                                     f"proprioception={env.proprioception})") from None
        return weights, meta

    def _policy(self, weights, meta):
        from forcegrasp.policy import Policy

        return Policy.from_weights(weights, meta, seed=0)

    def process(self, step: int, path: Path) -> Member | None:
        """Evaluate one checkpoint and update the top k; returns its Member if it entered."""
        self.current = step
        try:
            try:
                size = path.stat().st_size
                if size > MAX_POLICY_BYTES:
                    raise CheckpointRejected(f"{path}: {size} bytes is more than any policy file")
                data = path.read_bytes()
            except FileNotFoundError:
                log.warning("checkpoint %s vanished before it was evaluated", path)
                self.counters.missing_files += 1
                return None
            except OSError as exc:
                raise CheckpointRejected(f"{path}: cannot read: {exc}") from None
            weights, meta = self._check(data, str(path))
            policy = self._policy(weights, meta)
            t0 = time.perf_counter()
            result = self._score(policy, weights, meta, "eval", step)
            self.counters.episode_seconds += time.perf_counter() - t0
            log.info("step %d: score %.2f, success %.0f%% over %d episodes (%.1f s)", step, result.score,
                     100 * result.success_rate, result.episodes, time.perf_counter() - t0)
            if result.objects:
                log.info("step %d per object: %s", step, ", ".join(
                    f"{o} {v['success_rate']:.0%} ({v['score']:.1f})" for o, v in result.objects.items()))
            self.top.record(step, result.score, result.success_rate, result.episodes,
                            **({"conditions": result.conditions} if result.conditions else {}),
                            **({"objects": result.objects} if result.objects else {}))
            self.last_result = (step, result)
            member = None
            if self.top.would_enter(result.score, step):
                member, blob = self._rank(step, weights, meta, policy, result)
                evicted = self.top.admit(member, blob)
                self.counters.entered_top += 1
                log.info("step %d enters the top %d (rank score %.2f)%s; best is now %s", step, self.top.k,
                         member.rank_score, f", {', '.join(m.file for m in evicted)} leaves" if evicted else "",
                         self.top.best.file)
            self.top.commit()
            self.on_commit(step, result)
            self._prune_episode_logs(latest=step)
            self.counters.evaluations += 1  # counted once on disk: stats never run ahead of the index
            return member
        except CheckpointRejected as exc:
            self.failed.add(step)
            self.counters.bad_checkpoints += 1
            log.error("checkpoint %d rejected: %s", step, exc)
            return None
        finally:
            self.current = None

    def _prune_episode_logs(self, latest: int) -> None:
        """With ``keep_episode_logs = "top"``, delete the MCAP logs of checkpoints that are neither
        in the top k nor the latest evaluated: at paper settings each costs ~16 MB, 8 GB per 1 M steps."""
        if self.config.evaluator.keep_episode_logs != "top" or not self.episodes_dir.is_dir():
            return
        keep = {m.step for m in self.top.members} | {latest}
        for folder in self.episodes_dir.iterdir():
            if folder.is_dir() and folder.name.isdigit() and int(folder.name) not in keep:
                shutil.rmtree(folder, ignore_errors=True)
                self.counters.pruned_logs += 1

    def _rank(self, step: int, weights, meta: PolicyMetadata, policy, result: EvalResult) -> tuple[Member, bytes]:
        """Score a top-k newcomer on the ranking placements; its file carries the scores."""
        t0 = time.perf_counter()
        rank = self._score(policy, weights, meta, "rank", step)
        self.counters.rank_evaluations += 1
        self.counters.episode_seconds += time.perf_counter() - t0
        meta = dataclasses.replace(meta, eval_score=rank.score, extra={**meta.extra, "evaluation": {
            "step": step, "rank_score": rank.score, "rank_success_rate": rank.success_rate,
            "rank_episodes": rank.episodes, "eval_score": result.score, "eval_success_rate": result.success_rate,
            "eval_episodes": result.episodes, "run": self.config.run.name,
            **({"rank_conditions": rank.conditions, "eval_conditions": result.conditions} if rank.conditions else {}),
            **({"rank_objects": rank.objects, "eval_objects": result.objects,
                "object_aggregate": self.config.evaluator.object_aggregate} if rank.objects else {})}})
        blob = policy_to_bytes(weights, meta)
        member = Member(
            file=policy_file_name(step), step=step, score=result.score, success_rate=result.success_rate,
            episodes=result.episodes, rank_score=rank.score, rank_success_rate=rank.success_rate,
            rank_episodes=rank.episodes, sha256=sha256(blob), size=len(blob), object=meta.object_name or
            ("" if rank.objects else self.config.env.object), force_feedback=meta.force_feedback,
            policy_version=int(meta.extra.get("policy_version", 0) or 0), evaluated_at=time.time(),
            conditions=rank.conditions, objects=rank.objects)
        return member, blob

    def _rescore_members(self) -> None:
        for old in list(self.top.members):
            data = self.top.read_policy(old)
            weights, meta = load_policy_bytes(data)
            meta.extra = {k: v for k, v in meta.extra.items() if k != "evaluation"}
            policy = self._policy(weights, meta)
            result = self._score(policy, weights, meta, "eval", old.step)
            member, blob = self._rank(old.step, weights, meta, policy, result)
            self.top.replace(member, blob)
        self.top.commit()

    def evaluate_next(self) -> bool:
        """Score the next wanted snapshot, if any; returns whether one was taken."""
        nxt = self.next_checkpoint()
        if nxt is None:
            return False
        try:
            self.process(*nxt)
        except Interrupted:
            log.info("stopping: evaluation of step %d abandoned (redone after a restart)", nxt[0])
        except Exception:  # a bug or a full disk must not take the endpoint down with it
            log.exception("evaluating step %d failed; skipping it", nxt[0])
            self.failed.add(nxt[0])
            self.counters.bad_checkpoints += 1
        return True

    def on_commit(self, step: int, result: EvalResult) -> None:
        """Called after each evaluation is on disk (the service refreshes what it serves)."""

    def stats(self) -> dict:
        """The role's counters: what was scored, the latest checkpoint's and the best's success."""
        c = self.counters
        best = self.top.best
        return {
            "evaluations": c.evaluations,
            "rank_evaluations": c.rank_evaluations,
            "episodes": c.episodes,
            "episodes_per_s": c.episodes / c.episode_seconds if c.episode_seconds else None,
            "entered_top": c.entered_top,
            "pending": len(self.pending),
            "evaluating": self.current,
            "last_step": self.top.last_step,
            "skipped": c.skipped,
            "bad_checkpoints": c.bad_checkpoints,
            "missing_files": c.missing_files,
            "best_step": best.step if best else None,
            "best_score": best.rank_score if best else None,
            "best_success_rate": best.rank_success_rate if best else None,
            "best_episodes": best.rank_episodes if best else None,
            "best_objects": {o: v["success_rate"] for o, v in best.objects.items()} if best else {},
            "latest_step": self.last_result[0] if self.last_result else None,
            "latest_success_rate": self.last_result[1].success_rate if self.last_result else None,
            "latest_episodes": self.last_result[1].episodes if self.last_result else None,
            "top_scores": {str(m.step): m.score for m in self.top.members},
            "top_rank_scores": {str(m.step): m.rank_score for m in self.top.members},
            "top_count": len(self.top.members),
            "pruned_logs": c.pruned_logs,
        }

    def write_scalars(self, writer, step: int, result: EvalResult) -> None:
        """Deterministic success of each evaluated checkpoint and of the current best, by learner
        step, in the run's TensorBoard folder (next to the actors' online figures)."""
        writer.add_scalar("evaluator/checkpoint_success_rate", result.success_rate, step)
        writer.add_scalar("evaluator/checkpoint_return", result.score, step)
        best = self.top.best
        if best is not None:
            writer.add_scalar("evaluator/best_success_rate", best.rank_success_rate, step)
        writer.flush()
