"""Learner service: ingests actors' transitions from Zenoh into the replay buffer, trains SAC at
the configured update-to-data ratio, broadcasts policy weights, checkpoints, and resumes.

Zenoh's receive path only copies payloads into a bounded queue (a full queue pushes back on the
actors' blocking publishers); decoding, validation and training happen in this loop. Every bad
message is logged (the first few of each kind), counted by reason and dropped.

Files (named in `forcegrasp.rundir`): ``checkpoint.safetensors`` (learner state, written last,
marks a complete checkpoint), ``replay.npz``, ``policy.safetensors`` and ``checkpoints/policy-<step>``
files for the evaluator, ``tb/`` TensorBoard scalars, ``config.toml``.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import logging
import time
from pathlib import Path

import numpy as np

from forcegrasp.config import Config, add_config_arguments, config_from_args
from forcegrasp import task
from forcegrasp.policy import weights_of
from forcegrasp.protocol import (
    Checkpoint,
    Keys,
    Limits,
    ProtocolError,
    RejectCounter,
    Stats,
    Weights,
    decode_transitions,
    encode_checkpoint,
    encode_stats,
    encode_weights,
)
from forcegrasp.replay import ReplayBuffer
from forcegrasp.rundir import RunDir
from forcegrasp.runtime import open_service_session, policy_metadata, stop_on_signals
from forcegrasp.sac import SAC, sac_config
from forcegrasp.transport import (
    QueueSubscriber,
    close_session,
    declare_publisher,
    declare_queryable,
    declare_token,
)

log = logging.getLogger("forcegrasp.learner")
ACT_DIM = task.ACT_DIM
MAX_UPDATES_PER_LOOP = 8  # then look at the network again, so ingestion never starves
MAX_DRAIN_PER_LOOP = 512
MAX_UPDATE_DEBT = 10_000  # a learner slower than its actors trains below the target ratio


@dataclasses.dataclass
class ActorTrack:
    """What the learner knows about one actor's stream."""

    last_seq: int = -1
    epoch: int | None = None
    restarts: int = 0
    duplicates: int = 0
    ingested: int = 0
    gaps: int = 0
    staleness_sum: float = 0.0
    batches: int = 0
    rate_mark: tuple[float, int] = (0.0, 0)


class LearnerService:
    def __init__(self, config: Config):
        self.config = config
        self.keys = Keys(config.run.name)
        self.files = RunDir.of(config)
        self.dir = self.files.root
        self.dir.mkdir(parents=True, exist_ok=True)
        self.sac_cfg = sac_config(config)
        self.obs_dim = task.obs_dim(config.env.force_feedback)
        self.priv_dim = task.PRIV_DIM if self.sac_cfg.privileged_critic else 0
        self.limits = Limits(max_payload_bytes=config.learner.max_payload_mb * 2**20)
        self.rejects = RejectCounter()
        self.actors: dict[str, ActorTrack] = collections.defaultdict(ActorTrack)
        self.recent_episodes: collections.deque = collections.deque(maxlen=100)
        self.ingested = 0
        self.policy_version = 0
        self.latest_weights: bytes | None = None
        self.writer = None  # TensorBoard, opened by run()
        self.inbox = None
        self.episode_count = 0
        self._updates_due = 0.0
        self._last_checkpoint = 0
        self._last_policy = 0
        self._resume_or_start()

    # ------------------------------------------------------------------ state
    def _resume_or_start(self) -> None:
        ckpt = self.files.checkpoint
        if ckpt.exists():
            self.sac, extra = SAC.load_checkpoint(ckpt)
            replay = self.files.replay
            if replay.exists() and self.config.learner.snapshot_replay:
                self.buffer = ReplayBuffer.load(replay, capacity=self.sac_cfg.buffer_size)
            else:  # learner.snapshot_replay = false: networks and counters resume, the replay starts empty
                self.buffer = ReplayBuffer(self.obs_dim, ACT_DIM, self.sac_cfg.buffer_size, priv_dim=self.priv_dim)
            self.ingested = int(extra["ingested"])
            self.policy_version = int(extra["policy_version"])
            self._last_checkpoint = self._last_policy = self.ingested
            log.info("resumed from %s: %d transitions ingested, %d updates, %d in replay",
                     ckpt, self.ingested, self.sac.num_updates, len(self.buffer))
        else:
            self.sac = SAC(self.obs_dim, ACT_DIM, self.sac_cfg, priv_dim=self.priv_dim)
            self.buffer = ReplayBuffer(self.obs_dim, ACT_DIM, self.sac_cfg.buffer_size, priv_dim=self.priv_dim)
            self.files.config.write_text(self.config.to_toml())
        self.rng = np.random.default_rng(self.sac_cfg.seed + self.ingested)

    def metadata(self, score=None):
        return policy_metadata(self.config, self.sac_cfg.hidden, training_steps=self.ingested, score=score,
                               obs_norm=self.sac_cfg.obs_norm, policy_version=self.policy_version)

    def make_weights(self) -> bytes:
        """Encode the current actor as the next policy version (cached for weights/latest)."""
        self.policy_version += 1
        w = Weights(self.policy_version, self.sac.num_updates, weights_of(self.sac.deployed_actor),
                    meta={"policy_metadata": self.metadata().to_json()})
        self.latest_weights = encode_weights(w, self.limits)
        return self.latest_weights

    def save_policy(self) -> Path:
        """A policy snapshot for the evaluator (~350 KB): every ``evaluator.eval_every`` steps, the
        paper's test interval, far more often than the full checkpoint with its replay."""
        policy = self.sac.policy(self.metadata())
        self.files.checkpoints.mkdir(exist_ok=True)
        path = policy.save(self.files.snapshot(self.ingested))
        policy.save(self.files.latest_policy)
        self._last_policy = self.ingested
        return path

    def checkpoint(self) -> Path:
        """Replay and policy first, learner state last: the learner file marks a complete set."""
        if self.config.learner.snapshot_replay:
            self.buffer.save(self.files.replay)
        policy_path = self.save_policy()
        self.sac.save_checkpoint(self.files.checkpoint,
                                 extra={"ingested": self.ingested, "policy_version": self.policy_version})
        self._last_checkpoint = self.ingested
        return policy_path

    # ------------------------------------------------------------------ ingestion
    def ingest(self, key: str, payload: bytes) -> int:
        """Validate one TransitionBatch and add it to replay; returns transitions added (0 if dropped)."""
        try:
            batch = decode_transitions(payload, obs_dim=self.obs_dim, act_dim=ACT_DIM, priv_dim=self.priv_dim,
                                       limits=self.limits)
            sender = self.keys.actor_of(key)
            if batch.actor_id != sender:
                raise ProtocolError("bad_field", f"batch says actor {batch.actor_id!r} but came on {key!r}")
        except ProtocolError as exc:
            if self.rejects.reject(exc) <= 5:
                log.warning("dropped a message on %s: %s", key, exc)
            return 0
        track = self.actors[batch.actor_id]
        if batch.epoch != track.epoch:  # first contact, or a restarted actor counting from 0 again
            if track.epoch is not None:
                track.restarts += 1
            track.epoch, track.last_seq = batch.epoch, batch.seq - 1
        if batch.seq <= track.last_seq:
            track.duplicates += 1  # resent after an outage, already in replay
            return 0
        if batch.seq > track.last_seq + 1:
            track.gaps += batch.seq - track.last_seq - 1
        track.last_seq = batch.seq
        track.batches += 1
        track.ingested += batch.n
        track.staleness_sum += self.policy_version - batch.policy_version
        self.sac.observe(batch.obs)
        self.buffer.add_batch(batch.obs, batch.action, batch.reward, batch.next_obs, batch.terminated,
                              batch.horizon, batch.privileged, batch.next_privileged)
        if batch.has_episodes:
            for r, n, s in zip(batch.episode_returns, batch.episode_lengths, batch.episode_successes):
                self.recent_episodes.append((float(r), int(n), bool(s)))
                self.episode_count += 1
                if self.writer is not None:
                    self.writer.add_scalar("actors/episode_return", float(r), self.ingested + batch.n)
                    self.writer.add_scalar("actors/success", float(s), self.ingested + batch.n)
        self.rejects.accept()
        self.ingested += batch.n
        if len(self.buffer) >= self.sac_cfg.learning_starts:
            self._updates_due = min(self._updates_due + batch.n * self.sac_cfg.updates_per_step, MAX_UPDATE_DEBT)
        return batch.n

    # ------------------------------------------------------------------ training
    def train_some(self) -> dict:
        metrics = {}
        n = min(int(self._updates_due), MAX_UPDATES_PER_LOOP)
        for i in range(n):
            want = i == n - 1 and self.sac.num_updates % 50 < n
            out = self.sac.update(self.buffer.sample(self.sac_cfg.batch_size, self.rng), metrics=want)
            metrics = out or metrics
        self._updates_due -= n
        return metrics

    def headroom(self) -> float | None:
        """Transitions the learner will still take before it owes too many updates (None: no limit).

        The debt is the updates owed for data already ingested (``updates_per_step`` each);
        actors pause while it exceeds ``max_lead`` transitions' worth, so training holds the
        ratio however fast the actors are, and a learner with nothing owed never waits.
        """
        lead = self.config.learner.max_lead
        if lead == 0:
            return None
        return lead - self._updates_due / self.sac_cfg.updates_per_step

    def stats(self, elapsed: float, updates0: int, ingested0: int) -> dict:
        """Counters, and rates over the ``elapsed`` seconds since ``updates0``/``ingested0``."""
        now = time.monotonic()
        actors = {}
        for actor_id, t in self.actors.items():
            t_prev, n_prev = t.rate_mark
            rate = (t.ingested - n_prev) / (now - t_prev) if t_prev else 0.0
            t.rate_mark = (now, t.ingested)
            actors[actor_id] = {"ingested": t.ingested, "per_s": rate, "last_seq": t.last_seq, "gaps": t.gaps,
                                "restarts": t.restarts, "duplicates": t.duplicates,
                                "staleness": t.staleness_sum / t.batches if t.batches else 0.0}
        episodes = list(self.recent_episodes)
        return {
            "ingested": self.ingested,
            "updates": self.sac.num_updates,
            "updates_per_s": (self.sac.num_updates - updates0) / max(elapsed, 1e-9),
            "ingest_per_s": (self.ingested - ingested0) / max(elapsed, 1e-9),
            "replay_size": len(self.buffer),
            "policy_version": self.policy_version,
            "episodes": self.episode_count,
            "return_mean": float(np.mean([e[0] for e in episodes])) if episodes else None,
            "success_rate": float(np.mean([e[2] for e in episodes])) if episodes else None,
            "accepted": self.rejects.accepted,
            "rejected": self.rejects.total,
            "rejected_by_reason": self.rejects.counts(),
            "gaps": sum(t.gaps for t in self.actors.values()),
            "dropped_queue_full": self.inbox.dropped if self.inbox is not None else 0,
            "alpha": self.sac.alpha,
            "last_checkpoint": self._last_checkpoint,
            "actors": actors,
        }

    # ------------------------------------------------------------------ service loop
    def run(self, stop) -> None:
        from torch.utils.tensorboard import SummaryWriter

        cfg = self.config.learner
        session = open_service_session(self.config, "learner")
        self.writer = SummaryWriter(str(self.files.tensorboard))
        # A full queue blocks Zenoh for up to 5 s (back-pressure on the actors) before dropping.
        inbox = QueueSubscriber(session, self.keys.all_transitions, maxsize=cfg.ingest_queue, with_key=True,
                                put_timeout=5.0)
        self.inbox = inbox
        try:
            token = declare_token(session, self.keys.alive("learner", "0"))
            weights_pub = declare_publisher(session, self.keys.weights)
            ckpt_pub = declare_publisher(session, self.keys.checkpoints)
            stats_pub = declare_publisher(session, self.keys.stats("learner", "0"))
            progress_pub = declare_publisher(session, self.keys.progress)
            last_progress = 0.0
            self.make_weights()
            queryable = declare_queryable(session, self.keys.weights_latest, lambda: self.latest_weights)
            weights_pub.put(self.latest_weights)
            t0, updates0, ingested0 = time.monotonic(), self.sac.num_updates, self.ingested
            last_stats, last_broadcast, metrics = t0, self.sac.num_updates, {}
            while not stop.is_set():
                # Drain everything waiting (decoding is ~0.2 ms a batch): the replay, the
                # headroom the actors see and the update debt then all describe the same data.
                for drained in range(MAX_DRAIN_PER_LOOP):
                    item = inbox.get(timeout=0.0 if (drained or self._updates_due >= 1) else 0.01)
                    if item is None:
                        break
                    self.ingest(*item)
                if self._updates_due >= 1:
                    metrics = self.train_some() or metrics
                if self.sac.num_updates - last_broadcast >= cfg.broadcast_every:
                    weights_pub.put(self.make_weights())
                    last_broadcast = self.sac.num_updates
                path = None
                if self.ingested - self._last_checkpoint >= cfg.checkpoint_every:
                    path = self.checkpoint()
                elif self.ingested - self._last_policy >= self.config.evaluator.eval_every:
                    path = self.save_policy()
                if path is not None:
                    ckpt_pub.put(encode_checkpoint(Checkpoint(self.ingested, str(path), self.policy_version)))
                now = time.monotonic()
                if now - last_progress >= 0.05:
                    progress = {"ingested": self.ingested, "updates": self.sac.num_updates, "headroom": self.headroom(),
                                "acked": {a: {"epoch": t.epoch, "seq": t.last_seq} for a, t in self.actors.items()}}
                    progress_pub.put(encode_stats(Stats("learner", "progress", progress)))
                    last_progress = now
                if now - last_stats >= cfg.stats_every_s:
                    values = self.stats(now - t0, updates0, ingested0)  # rates over this stats window
                    t0, updates0, ingested0 = now, self.sac.num_updates, self.ingested
                    stats_pub.put(encode_stats(Stats("learner", "0", values)))
                    self._log_scalars(values, metrics)
                    last_stats = now
            queryable.undeclare()
            token.undeclare()
        finally:
            inbox.close()
            close_session(session)
            self.writer.close()

    def _log_scalars(self, values: dict, metrics: dict) -> None:
        w, step = self.writer, self.ingested
        for key in ("updates_per_s", "ingest_per_s", "replay_size", "rejected", "gaps", "alpha"):
            w.add_scalar(f"learner/{key}", values[key], step)
        for key in ("return_mean", "success_rate"):
            if values[key] is not None:
                w.add_scalar(f"actors/{key}_100", values[key], step)
        for k, v in metrics.items():
            w.add_scalar(f"sac/{k}", v, step)
        staleness = [a["staleness"] for a in values["actors"].values()]
        if staleness:
            w.add_scalar("actors/staleness", float(np.mean(staleness)), step)
        w.flush()
        log.info("ingested %d  updates %d (%.0f/s)  ingest %.0f/s  replay %d  v%d  episodes %d  return %s  "
                 "success %s  rejected %d  gaps %d", values["ingested"], values["updates"], values["updates_per_s"],
                 values["ingest_per_s"], values["replay_size"], values["policy_version"], values["episodes"],
                 "-" if values["return_mean"] is None else f"{values['return_mean']:.1f}",
                 "-" if values["success_rate"] is None else f"{values['success_rate']:.0%}",
                 values["rejected"], values["gaps"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp learner", description=__doc__.splitlines()[0])
    add_config_arguments(parser)
    args = parser.parse_args(argv)
    config = config_from_args(args)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    stop = stop_on_signals()
    service = LearnerService(config)
    log.info("learner: run %s, %s, listening on %s", config.run.name, config.env.object, config.network.learner_listen)
    service.run(stop)
    service.checkpoint()
    log.info("learner: stopped at %d transitions, checkpoint written", service.ingested)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
