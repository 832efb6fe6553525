"""Actor service: the actor role (:class:`forcegrasp.acting.Actor`) wired to Zenoh.

- Publishes its batches as ``TransitionBatch`` messages on ``forcegrasp/<run>/transitions/<actor>``
  (per-process ``epoch``, per-actor ``seq``, the policy version it acted with, episodes that
  ended); what is kept until acknowledged and resent after an outage is
  :class:`forcegrasp.delivery.Outbox`.
- Asks ``weights/latest`` at start, so a late joiner acts with current weights at once, then
  keeps the newest broadcast from ``weights``; a bad weights message is counted and ignored.
- Pauses while the learner's published headroom is used up (the rate limiter that holds the
  update-to-data ratio); when no learner is there it runs on, filling its bounded outbox.
- It never exits on its own: only SIGINT/SIGTERM stop it.
"""

from __future__ import annotations

import argparse
import logging
import os
import time

import numpy as np

from forcegrasp.acting import Actor
from forcegrasp.config import Config, add_config_arguments, config_from_args
from forcegrasp.delivery import Outbox
from forcegrasp.policy import configure_threads
from forcegrasp.policy_file import PolicyFileError, PolicyMetadata
from forcegrasp.protocol import (
    Keys,
    ProtocolError,
    RejectCounter,
    Stats,
    decode_progress,
    decode_weights,
    encode_stats,
    encode_transitions,
)
from forcegrasp.runtime import open_service_session, stop_on_signals
from forcegrasp.transport import (
    declare_publisher,
    declare_token,
    has_subscribers,
    query_bytes,
    subscribe_latest,
    take_latest,
)

log = logging.getLogger("forcegrasp.actor")


class ActorService(Actor):
    """The actor role plus its outbox and the wire."""

    def __init__(self, config: Config, actor_id: str, seed: int | None = None):
        super().__init__(config, actor_id, seed)
        self.keys = Keys(config.run.name)
        self.epoch = int.from_bytes(os.urandom(4), "little")  # tells the learner this is a new process
        self.seq = 0
        self.outbox = Outbox(actor_id, self.epoch, config.actor.max_buffered_batches)
        self.weight_rejects = RejectCounter()
        self.invalid_batches = 0
        self.paused_s = 0.0

    def apply_weights(self, payload: bytes) -> bool:
        """Validate a weights message and swap the policy; a bad one is counted and ignored."""
        try:
            w = decode_weights(payload)
            meta = PolicyMetadata.from_json(w.meta.get("policy_metadata", ""))
            params = {k: np.array(v) for k, v in w.params.items()}  # own the memory, not the message's
            return self.update(params, meta, w.policy_version)
        except (ProtocolError, PolicyFileError, ValueError, TypeError, KeyError) as exc:
            self.weight_rejects.reject(exc if isinstance(exc, ProtocolError) else "bad_weights")
            log.warning("actor %s: rejected weights message: %s", self.actor_id, exc)
            return False

    def apply_progress(self, payload: bytes) -> None:
        try:
            self.outbox.on_progress(decode_progress(payload))
        except ProtocolError:
            self.weight_rejects.reject("bad_progress")

    def step_all(self) -> None:
        """One step of every env; a full batch is encoded and queued in the outbox."""
        batch = self.step()
        if batch is None:
            return
        batch.seq, batch.epoch = self.seq, self.epoch
        try:
            payload = encode_transitions(batch)
        except ProtocolError as exc:  # e.g. a diverged simulation produced NaN: never send it
            log.error("actor %s: dropped an invalid batch: %s", self.actor_id, exc)
            self.invalid_batches += 1
            return
        self.outbox.put(self.seq, payload, batch.n)
        self.seq += 1

    def stats(self) -> dict:
        out = self.outbox.stats()
        return {**super().stats(), "seq": self.seq, **out,
                "dropped_batches": out["dropped_batches"] + self.invalid_batches,
                "rejected_weights": self.weight_rejects.total, "paused_s": round(self.paused_s, 3)}

    # ------------------------------------------------------------------ service loop
    def run(self, stop) -> None:
        session = open_service_session(self.config, "actor", identity=self.actor_id)
        try:
            keys = self.keys
            token = declare_token(session, keys.alive("actor", self.actor_id))
            transitions = declare_publisher(session, keys.transitions(self.actor_id))
            stats_pub = declare_publisher(session, keys.stats("actor", self.actor_id))
            weights_sub = subscribe_latest(session, keys.weights)
            progress_sub = subscribe_latest(session, keys.progress)
            last_query = -1e9
            last_stats = 0.0
            t0 = time.monotonic()
            while not stop.is_set():
                now = time.monotonic()
                latest = take_latest(weights_sub)
                if latest is not None:
                    self.apply_weights(latest)
                elif self.policy is None and now - last_query > 1.0:
                    last_query = now  # no weights yet (start, or learner away): ask, at most 1/s
                    reply = query_bytes(session, keys.weights_latest, timeout=0.5)
                    if reply is not None:
                        self.apply_weights(reply)
                progress = take_latest(progress_sub)
                if progress is not None:
                    self.apply_progress(progress)
                if now - last_stats > 1.0:
                    last_stats = now
                    values = {**self.stats(), "steps_per_s": self.steps / max(now - t0, 1e-9)}
                    stats_pub.put(encode_stats(Stats("actor", self.actor_id, values)))
                if self.outbox.must_wait(has_subscribers(transitions)):
                    time.sleep(0.002)
                    self.paused_s += 0.002
                    continue
                self.step_all()
                self.outbox.flush(has_subscribers(transitions), transitions.put)
            self._drain(transitions, progress_sub)
            token.undeclare()
        finally:
            from forcegrasp.transport import close_session

            close_session(session)


    def _drain(self, transitions, progress_sub, timeout_s: float = 3.0) -> None:
        """On a clean stop: hand the learner what waits and collect its acknowledgements, so the
        final count says what the learner has (a killed actor loses only its unacked batches)."""
        deadline = time.monotonic() + timeout_s
        while (self.outbox.waiting or self.outbox.unacked) and time.monotonic() < deadline:
            present = has_subscribers(transitions)
            self.outbox.flush(present, transitions.put)
            progress = take_latest(progress_sub)
            if progress is not None:
                self.apply_progress(progress)
            time.sleep(0.02)
        out = self.outbox.stats()
        log.info("actor %s: the learner acknowledged %d transitions; %d batches unacknowledged at exit",
                 self.actor_id, out["acked_transitions"], out["unacked_batches"] + out["buffered_batches"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp actor", description=__doc__.splitlines()[0])
    parser.add_argument("--id", default=None, help="actor id (default: actor-<host>-<pid>, unique per machine)")
    parser.add_argument("--seed", type=int, default=None, help="env and exploration seed (default: random)")
    add_config_arguments(parser)
    args = parser.parse_args(argv)
    config = config_from_args(args)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    import socket

    actor_id = args.id or f"actor-{socket.gethostname()}-{os.getpid()}"
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(4), "little")
    configure_threads(1)  # a batch of a few observations gains nothing from more; leave cores to the envs
    stop = stop_on_signals()
    service = ActorService(config, actor_id, seed=seed)
    log.info("actor %s: %d envs of %s, run %s", actor_id, len(service.envs), ", ".join(service.env_objects),
             config.run.name)
    service.run(stop)
    log.info("actor %s: stopped after %d steps", actor_id, service.steps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
