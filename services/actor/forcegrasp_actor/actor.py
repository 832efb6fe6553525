"""Actor service: steps several FunctionalGrasp envs with its copy of the policy and streams
transitions to the learner over Zenoh.

- Acts uniformly at random for its first ``actor.random_steps`` env steps, then samples from the
  latest policy it has; one batched forward pass serves all its envs.
- Publishes ``TransitionBatch`` messages (per-actor sequence numbers, the policy version it acted
  with, episodes that ended) on ``forcegrasp/<run>/transitions/<actor>``; with the learner's
  ``n_step`` > 1 they carry n-step returns and their horizons, with ``privileged_critic`` the
  simulator state the critic sees (read from the same configuration as the learner).
- Asks ``weights/latest`` at start, so a late joiner acts with current weights at once, then
  keeps the newest broadcast from ``weights``.
- Pauses while the learner's published headroom is used up (the rate limiter that holds the
  update-to-data ratio); when no learner is there it runs on.
- While no learner listens it keeps a bounded outbox (oldest batches dropped first) and sends it
  when a learner is back. Sent batches stay until the learner acknowledges them (in its
  progress messages); when the link comes back, unacknowledged ones are sent again, so an
  outage loses nothing that fits the buffer (the learner drops the duplicates by ``seq``). It never exits on its own: only SIGINT/SIGTERM stop it.
"""

from __future__ import annotations

import argparse
import collections
import logging
import os
import time

import numpy as np

from forcegrasp.config import Config, add_config_arguments, config_from_args
from forcegrasp import task
from forcegrasp.nstep import NStepAccumulator
from forcegrasp.sac import sac_config
from forcegrasp.policy import Policy, configure_threads
from forcegrasp.policy_file import PolicyFileError, PolicyMetadata
from forcegrasp.protocol import (
    Keys,
    ProtocolError,
    RejectCounter,
    Stats,
    TransitionBatch,
    decode_stats,
    decode_weights,
    encode_stats,
    encode_transitions,
)
from forcegrasp.runtime import make_env, open_service_session, stop_on_signals
from forcegrasp.transport import (
    declare_publisher,
    declare_token,
    has_subscribers,
    query_bytes,
    subscribe_latest,
    take_latest,
)

log = logging.getLogger("forcegrasp.actor")


class ActorService:
    def __init__(self, config: Config, actor_id: str, seed: int | None = None):
        self.config = config
        self.actor_id = actor_id
        self.keys = Keys(config.run.name)
        n = config.actor.envs_per_actor
        self.envs = [make_env(config) for _ in range(n)]
        base_seed = config.run.seed + 1000 if seed is None else seed
        self.rng = np.random.default_rng(base_seed)
        self.obs = np.stack([env.reset(seed=base_seed + i)[0] for i, env in enumerate(self.envs)])
        self.obs_dim, self.act_dim = self.obs.shape[1], task.ACT_DIM
        sac = sac_config(config)  # the learner's n-step horizon, discount and critic inputs
        self.privileged = bool(sac.privileged_critic)
        self.priv = np.stack([env.privileged_state() for env in self.envs]) if self.privileged else None
        self.nstep = [NStepAccumulator(sac.n_step, sac.gamma) for _ in self.envs]
        self.policy: Policy | None = None
        self.policy_version = 0
        self.steps = 0
        self.seq = 0
        self.episodes = 0
        self.successes = 0
        self.sent_batches = 0
        self.dropped_batches = 0
        self.weight_rejects = RejectCounter()
        self.epoch = int.from_bytes(os.urandom(4), "little")  # tells the learner this is a new process
        self.outbox: collections.deque[tuple[int, bytes]] = collections.deque()
        self.unacked: collections.deque[tuple[int, bytes]] = collections.deque()  # sent, not yet ingested
        self.resent_batches = 0
        self._pending: list[tuple] = []
        self._ended: list[tuple[float, int, bool]] = []
        self._headroom: float | None = None  # from the learner's progress messages
        self._sent_since_progress = 0
        self.paused_s = 0.0
        self._returns = np.zeros(n)
        self._lengths = np.zeros(n, dtype=np.int64)

    # ------------------------------------------------------------------ policy
    def apply_weights(self, payload: bytes) -> bool:
        """Validate a weights message and swap the policy; a bad one is counted and ignored."""
        try:
            w = decode_weights(payload)
            meta = PolicyMetadata.from_json(w.meta.get("policy_metadata", ""))
            if meta.obs_dim != self.obs_dim or meta.act_dim != self.act_dim:
                raise ProtocolError("shape", f"policy is {meta.obs_dim}->{meta.act_dim}, env is {self.obs_dim}->{self.act_dim}")
            if w.policy_version <= self.policy_version and self.policy is not None:
                return False  # an older broadcast overtaken by a query reply, say
            params = {k: np.array(v) for k, v in w.params.items()}  # own the memory, not the message's
            self.policy = Policy.from_weights(params, meta, seed=int(self.rng.integers(2**31)))
            self.policy_version = w.policy_version
            return True
        except (ProtocolError, PolicyFileError, ValueError, TypeError, KeyError) as exc:
            self.weight_rejects.reject(exc if isinstance(exc, ProtocolError) else "bad_weights")
            log.warning("actor %s: rejected weights message: %s", self.actor_id, exc)
            return False

    def apply_progress(self, payload: bytes) -> None:
        try:
            values = decode_stats(payload).values
            headroom = values.get("headroom")
            self._headroom = None if headroom is None else float(headroom)
            self._sent_since_progress = 0
            acked = (values.get("acked") or {}).get(self.actor_id)
            if acked and acked.get("epoch") == self.epoch and acked.get("seq") is not None:
                while self.unacked and self.unacked[0][0] <= acked["seq"]:
                    self.unacked.popleft()
        except (ProtocolError, TypeError, ValueError):
            self.weight_rejects.reject("bad_progress")

    def must_wait(self, learner_present: bool) -> bool:
        """True while a live learner says the actors are ahead of its update-to-data ratio.

        A learner busy in a long step sends no news but is still there (its subscriber still
        matches): its last word holds. A learner that is gone releases the actor, which then
        fills its bounded outbox.
        """
        if self._headroom is None or not learner_present:
            return False
        return self._headroom - self._sent_since_progress <= 0

    def act(self) -> np.ndarray:
        if self.steps < self.config.actor.random_steps or self.policy is None:
            return self.rng.uniform(-1.0, 1.0, (len(self.envs), self.act_dim)).astype(np.float32)
        return self.policy(self.obs, deterministic=False).astype(np.float32)

    # ------------------------------------------------------------------ stepping
    def step_all(self) -> None:
        """One step of every env; finished episodes reset at once (the transition keeps the true
        last observation, with ``terminated`` marking real terminal states). Transitions leave
        through each env's n-step accumulator (one-step ones when ``n_step`` is 1)."""
        actions = self.act()
        for i, env in enumerate(self.envs):
            next_obs, reward, terminated, truncated, info = env.step(actions[i])
            next_priv = env.privileged_state() if self.privileged else None
            priv = self.priv[i].copy() if self.privileged else None
            for t in self.nstep[i].push(self.obs[i].copy(), actions[i], reward, next_obs, terminated, truncated,
                                        priv, next_priv):
                self._pending.append(t)
            self._returns[i] += reward
            self._lengths[i] += 1
            if terminated or truncated:
                self._ended.append((self._returns[i], int(self._lengths[i]), bool(info["success"])))
                self.episodes += 1
                self.successes += bool(info["success"])
                self._returns[i], self._lengths[i] = 0.0, 0
                next_obs, _ = env.reset()
                if self.privileged:
                    next_priv = env.privileged_state()
            self.obs[i] = next_obs
            if self.privileged:
                self.priv[i] = next_priv
        self.steps += len(self.envs)
        if len(self._pending) >= self.config.actor.publish_batch:
            self._package()

    def _package(self) -> None:
        p = self._pending
        obs, action, next_obs = (np.array([getattr(t, k) for t in p]) for k in ("obs", "action", "next_obs"))
        reward, term, trunc = (np.array([getattr(t, k) for t in p]) for k in ("reward", "terminated", "truncated"))
        extras = {}
        if any(t.horizon != 1 for t in p):
            extras["horizon"] = np.array([t.horizon for t in p], np.int32)
        if self.privileged:
            extras["privileged"] = np.array([t.extra for t in p], np.float32)
            extras["next_privileged"] = np.array([t.next_extra for t in p], np.float32)
        episodes = {}
        if self._ended:
            r, n, s = zip(*self._ended)
            episodes = dict(
                episode_returns=np.array(r, np.float32),
                episode_lengths=np.array(n, np.int32),
                episode_successes=np.array(s, bool),
            )
        batch = TransitionBatch(
            actor_id=self.actor_id,
            seq=self.seq,
            epoch=self.epoch,
            policy_version=self.policy_version,
            obs=obs,
            action=action,
            reward=reward,
            next_obs=next_obs,
            terminated=term,
            truncated=trunc,
            **episodes,
            **extras,
        )
        try:
            payload = encode_transitions(batch)
        except ProtocolError as exc:  # e.g. a diverged simulation produced NaN: never send it
            log.error("actor %s: dropped an invalid batch: %s", self.actor_id, exc)
            self.dropped_batches += 1
        else:
            self.outbox.append((self.seq, payload))
            self.seq += 1
            while len(self.outbox) + len(self.unacked) > self.config.actor.max_buffered_batches:
                (self.unacked or self.outbox).popleft()  # the oldest go first
                self.dropped_batches += 1
        self._pending.clear()
        self._ended.clear()

    def stats(self) -> dict:
        return {
            "steps": self.steps,
            "episodes": self.episodes,
            "successes": self.successes,
            "policy_version": self.policy_version,
            "seq": self.seq,
            "sent_batches": self.sent_batches,
            "buffered_batches": len(self.outbox),
            "unacked_batches": len(self.unacked),
            "resent_batches": self.resent_batches,
            "dropped_batches": self.dropped_batches,
            "rejected_weights": self.weight_rejects.total,
            "paused_s": round(self.paused_s, 3),
        }

    # ------------------------------------------------------------------ service loop
    def run(self, stop) -> None:
        session = open_service_session(self.config, "actor")
        try:
            keys = self.keys
            token = declare_token(session, keys.alive("actor", self.actor_id))
            transitions = declare_publisher(session, keys.transitions(self.actor_id))
            stats_pub = declare_publisher(session, keys.stats("actor", self.actor_id))
            weights_sub = subscribe_latest(session, keys.weights)
            progress_sub = subscribe_latest(session, keys.progress)
            last_query = -1e9
            was_present = False
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
                if self.must_wait(has_subscribers(transitions)):
                    time.sleep(0.002)
                    self.paused_s += 0.002
                    continue
                self.step_all()
                present = has_subscribers(transitions)
                if present and not was_present and self.unacked:
                    # A learner (back) after an outage: what it may have missed goes first.
                    self.resent_batches += len(self.unacked)
                    self.outbox.extendleft(reversed(self.unacked))
                    self.unacked.clear()
                was_present = present
                while present and self.outbox:
                    item = self.outbox.popleft()
                    transitions.put(item[1])
                    self.unacked.append(item)
                    self.sent_batches += 1
                    self._sent_since_progress += self.config.actor.publish_batch
            token.undeclare()
        finally:
            from forcegrasp.transport import close_session

            close_session(session)


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
    log.info("actor %s: %d envs of %s, run %s", actor_id, len(service.envs), config.env.object, config.run.name)
    service.run(stop)
    log.info("actor %s: stopped after %d steps", actor_id, service.steps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
