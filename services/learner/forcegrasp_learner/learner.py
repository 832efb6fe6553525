"""Learner service: the learner role (:class:`forcegrasp.learning.Learner`) wired to Zenoh.

It ingests actors' transitions into the replay buffer, trains at the configured update-to-data
ratio, broadcasts policy weights, tells the actors its headroom and acknowledgements (the
``progress`` message), announces snapshots to the evaluator, checkpoints and resumes.

Zenoh's receive path only copies payloads into a bounded queue (a full queue pushes back on the
actors' blocking publishers); decoding, validation and training happen in this loop. Every bad
message is logged (the first few of each kind), counted by reason and dropped; resends and
restarts are told apart by :class:`forcegrasp.delivery.Streams`.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from forcegrasp import task
from forcegrasp.config import Config, add_config_arguments, config_from_args
from forcegrasp.delivery import Streams
from forcegrasp.learning import Learner
from forcegrasp.protocol import (
    Checkpoint,
    Keys,
    Limits,
    Progress,
    ProtocolError,
    RejectCounter,
    Stats,
    decode_transitions,
    encode_checkpoint,
    encode_progress,
    encode_stats,
    encode_weights,
)
from forcegrasp.runtime import open_service_session, stop_on_signals
from forcegrasp.transport import (
    QueueSubscriber,
    close_session,
    declare_publisher,
    declare_queryable,
    declare_token,
)

log = logging.getLogger("forcegrasp.learner")
MAX_UPDATES_PER_LOOP = 8  # then look at the network again, so ingestion never starves
MAX_DRAIN_PER_LOOP = 512


class LearnerService(Learner):
    """The learner role plus what the network needs: stream checks, counters, the wire."""

    def __init__(self, config: Config):
        super().__init__(config)
        self.keys = Keys(config.run.name)
        self.dir = self.files.root
        self.limits = Limits(max_payload_bytes=config.learner.max_payload_mb * 2**20)
        self.rejects = RejectCounter()
        # Each actor's last admitted (epoch, seq) travels with the checkpoint: after a restart a
        # batch that was ingested before it but whose acknowledgement never left is a duplicate.
        self.streams = Streams.restore(self.resumed_extra.get("streams", {}))
        self.latest_weights: bytes | None = None
        self.writer = None  # TensorBoard, opened by run()
        self.inbox = None
        self.on_episode = self._episode_scalars

    def _episode_scalars(self, episode_return: float, success: bool, step: int) -> None:
        if self.writer is not None:
            self.writer.add_scalar("actors/episode_return", episode_return, step)
            self.writer.add_scalar("actors/success", float(success), step)

    def make_weights(self) -> bytes:
        """Encode the current actor as the next policy version (cached for weights/latest)."""
        self.latest_weights = encode_weights(self.weights(), self.limits)
        return self.latest_weights

    # ------------------------------------------------------------------ ingestion
    def ingest(self, key: str, payload: bytes) -> int:
        """Validate one TransitionBatch and add it to replay; returns transitions added (0 if dropped)."""
        try:
            batch = decode_transitions(payload, obs_dim=self.obs_dim, act_dim=task.ACT_DIM, priv_dim=self.priv_dim,
                                       limits=self.limits)
            sender = self.keys.actor_of(key)
            if batch.actor_id != sender:
                raise ProtocolError("bad_field", f"batch says actor {batch.actor_id!r} but came on {key!r}")
        except ProtocolError as exc:
            if self.rejects.reject(exc) <= 5:
                log.warning("dropped a message on %s: %s", key, exc)
            return 0
        foreign = self.foreign_objects(batch)
        if foreign:  # an actor started with other objects: its data would train what this run does not
            if self.rejects.reject("foreign_object") <= 5:
                log.warning("dropped a batch of actor %s: it steps %s, not among this run's objects (%s)",
                            batch.actor_id, ", ".join(foreign), ", ".join(self.objects))
            return 0
        if not self.streams.admit(batch, self.policy_version):
            return 0  # resent after an outage, already in replay
        self.rejects.accept()
        return self.observe(batch)

    def checkpoint_extra(self) -> dict:
        return {"streams": self.streams.snapshot()}

    def progress(self) -> Progress:
        return Progress(self.ingested, self.sac.num_updates, self.headroom(), self.streams.acked())

    def stats(self, elapsed: float, updates0: int, ingested0: int) -> dict:
        """The role's counters plus what the network adds: rejects, gaps, per-actor streams."""
        return {
            **super().stats(elapsed, updates0, ingested0),
            "accepted": self.rejects.accepted,
            "rejected": self.rejects.total,
            "rejected_by_reason": self.rejects.counts(),
            "gaps": self.streams.gaps,
            "dropped_queue_full": self.inbox.dropped if self.inbox is not None else 0,
            "actors": self.streams.stats(),
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
                    item = inbox.get(timeout=0.0 if (drained or self.updates_due >= 1) else 0.01)
                    if item is None:
                        break
                    self.ingest(*item)
                if self.updates_due >= 1:
                    metrics = self.train(MAX_UPDATES_PER_LOOP) or metrics
                if self.sac.num_updates - last_broadcast >= cfg.broadcast_every:
                    weights_pub.put(self.make_weights())
                    last_broadcast = self.sac.num_updates
                path = self.save_due()
                if path is not None:
                    ckpt_pub.put(encode_checkpoint(Checkpoint(self.ingested, str(path), self.policy_version)))
                now = time.monotonic()
                if now - last_progress >= 0.05:
                    progress_pub.put(encode_progress(self.progress()))
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
        self.write_scalars(self.writer, values, metrics)
        staleness = [a["staleness"] for a in values["actors"].values()]
        if staleness:
            self.writer.add_scalar("actors/staleness", float(np.mean(staleness)), self.ingested)
        self.writer.flush()
        sending = sorted(a for a, v in values["actors"].items() if v["per_s"] > 0)
        log.info("ingested %d  updates %d (%.0f/s)  ingest %.0f/s  replay %d  v%d  episodes %d  return %s  "
                 "success %s  rejected %d  gaps %d  actors %d sending: %s", values["ingested"], values["updates"],
                 values["updates_per_s"], values["ingest_per_s"], values["replay_size"], values["policy_version"],
                 values["episodes"], "-" if values["return_mean"] is None else f"{values['return_mean']:.1f}",
                 "-" if values["success_rate"] is None else f"{values['success_rate']:.0%}",
                 values["rejected"], values["gaps"], len(sending),
                 " ".join(sending[:8]) + (f" +{len(sending) - 8}" if len(sending) > 8 else ""))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp learner", description=__doc__.splitlines()[0])
    add_config_arguments(parser)
    args = parser.parse_args(argv)
    config = config_from_args(args)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    stop = stop_on_signals()
    service = LearnerService(config)
    log.info("learner: run %s, %s, listening on %s", config.run.name, ", ".join(service.objects),
             config.network.learner_listen)
    service.run(stop)
    service.checkpoint()
    log.info("learner: stopped at %d transitions, checkpoint written", service.ingested)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
