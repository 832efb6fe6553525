"""The learner role: SAC, its replay buffer, the update-to-data ratio and the checkpoint recipe of
a run directory. No network: the learner service feeds it validated batches from Zenoh and
broadcasts what it gives; ``forcegrasp train`` feeds it from an actor in the same process.

Files (named in :mod:`forcegrasp.rundir`): ``checkpoint.safetensors`` (learner state, written
last, marks a complete checkpoint), ``replay.npz`` (with ``learner.snapshot_replay``),
``policy.safetensors`` and ``checkpoints/policy-<step>`` snapshots every ``evaluator.eval_every``
transitions (the paper tests every 2,000 steps), ``config.toml``.
"""

from __future__ import annotations

import collections
import logging
from pathlib import Path

import numpy as np

from forcegrasp import task
from forcegrasp.config import Config
from forcegrasp.multi_object import run_objects
from forcegrasp.policy import weights_of
from forcegrasp.protocol import TransitionBatch, Weights
from forcegrasp.replay import ReplayBuffer
from forcegrasp.rundir import RunDir
from forcegrasp.runtime import policy_metadata
from forcegrasp.recipes import sac_config
from forcegrasp.sac import SAC

log = logging.getLogger("forcegrasp.learner")
#: Updates a learner may owe. Past it the oldest debt is forgone (counted in ``updates_forgone``):
#: a backlog the actors filled while no learner listened is trained on once, not for hours.
MAX_UPDATE_DEBT = 10_000


class Learner:
    """Takes transitions (:meth:`observe`), trains what they are owed (:meth:`train`), gives
    weights (:meth:`weights`), and saves/restores itself in its run directory."""

    def __init__(self, config: Config):
        self.config = config
        self.files = RunDir.of(config)
        self.files.root.mkdir(parents=True, exist_ok=True)
        self.sac_cfg = sac_config(config)
        self.obs_dim = task.obs_dim(config.env.force_feedback, config.env.torque_history, config.env.proprioception)
        self.priv_dim = task.PRIV_DIM if self.sac_cfg.privileged_critic else 0
        self.recent_episodes: collections.deque = collections.deque(maxlen=100)  # (return, length, success)
        self.objects = run_objects(config.env)  # the run's objects: batches naming another are refused
        self.by_object = {o: collections.deque(maxlen=100) for o in self.objects}  # success of the last 100 each
        self.object_episodes = dict.fromkeys(self.objects, 0)
        self.episode_count = 0
        # the conditions the recent transitions were drawn under (privileged "domain": ln mass scale,
        # noise sigma), per batch: how far a randomisation curriculum has opened the ranges
        self.recent_domain: collections.deque = collections.deque(maxlen=200)
        self.ingested = 0
        self.policy_version = 0
        self.updates_due = 0.0
        self.updates_forgone = 0.0  # debt dropped at MAX_UPDATE_DEBT (each one an update never made)
        self.last_checkpoint = 0
        self.last_policy = 0
        self.on_episode = None  # called (return, success, step) per finished episode, e.g. for TensorBoard
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
                self.buffer = self._empty_replay()
            self.ingested = int(extra["ingested"])
            self.policy_version = int(extra["policy_version"])
            self.resumed_extra = extra
            self.last_checkpoint = self.last_policy = self.ingested
            log.info("resumed from %s: %d transitions ingested, %d updates, %d in replay",
                     ckpt, self.ingested, self.sac.num_updates, len(self.buffer))
        else:
            self.resumed_extra = {}
            self.sac = SAC(self.obs_dim, task.ACT_DIM, self.sac_cfg, priv_dim=self.priv_dim)
            self.buffer = self._empty_replay()
            self.files.config.write_text(self.config.to_toml())
        self.rng = np.random.default_rng(self.sac_cfg.seed + self.ingested)

    def _empty_replay(self) -> ReplayBuffer:
        return ReplayBuffer(self.obs_dim, task.ACT_DIM, self.sac_cfg.buffer_size, priv_dim=self.priv_dim)

    @property
    def resumed(self) -> bool:
        return self.ingested > 0

    def metadata(self, score=None):
        return policy_metadata(self.config, self.sac_cfg.hidden, training_steps=self.ingested, score=score,
                               obs_norm=self.sac_cfg.obs_norm, policy_version=self.policy_version)

    # ------------------------------------------------------------------ taking data, training
    def observe(self, batch: TransitionBatch) -> int:
        """Add one batch (already validated and new) to replay; returns the transitions added."""
        self.sac.observe(batch.obs)
        self.buffer.add_batch(batch.obs, batch.action, batch.reward, batch.next_obs, batch.terminated,
                              batch.horizon, batch.privileged, batch.next_privileged)
        self.ingested += batch.n
        if batch.privileged is not None:
            domain = batch.privileged[:, task.DOMAIN]
            self.recent_domain.append((float(np.exp(domain[:, 0].min())), float(domain[:, 1].max())))
        if batch.has_episodes:
            names = ([batch.objects[i] for i in batch.episode_objects] if batch.episode_objects is not None
                     else [None] * len(batch.episode_returns))  # a sender that names no object
            for r, n, s, o in zip(batch.episode_returns, batch.episode_lengths, batch.episode_successes, names):
                self.recent_episodes.append((float(r), int(n), bool(s)))
                if o in self.by_object:
                    self.by_object[o].append(bool(s))
                    self.object_episodes[o] += 1
                self.episode_count += 1
                if self.on_episode is not None:
                    self.on_episode(float(r), bool(s), self.ingested)
        if len(self.buffer) >= self.sac_cfg.learning_starts:
            owed = self.updates_due + batch.n * self.sac_cfg.updates_per_step
            if owed > MAX_UPDATE_DEBT:
                if not self.updates_forgone:
                    log.warning("learner owes more than %d updates (a backlog from before it listened, or "
                                "learner.max_lead = 0 with fast actors): the excess is forgone, counted in "
                                "updates_forgone", MAX_UPDATE_DEBT)
                self.updates_forgone += owed - MAX_UPDATE_DEBT
                owed = MAX_UPDATE_DEBT
            self.updates_due = owed
        return batch.n

    def train(self, max_updates: int) -> dict:
        """Up to ``max_updates`` of the updates owed; returns the last update's metrics (every ~50)."""
        metrics = {}
        n = min(int(self.updates_due), max_updates)
        for i in range(n):
            want = i == n - 1 and self.sac.num_updates % 50 < n
            out = self.sac.update(self.buffer.sample(self.sac_cfg.batch_size, self.rng), metrics=want)
            metrics = out or metrics
        self.updates_due -= n
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
        return lead - self.updates_due / self.sac_cfg.updates_per_step

    def foreign_objects(self, batch: TransitionBatch) -> list[str]:
        """The objects a batch names that this run does not train (the learner refuses such a batch)."""
        return sorted(set(batch.objects or ()) - set(self.objects))

    def episode_stats(self) -> dict:
        """Mean return and success over the last 100 episodes the actors finished (online figures);
        with several objects, each object's success over its own last 100 (``objects``)."""
        episodes = list(self.recent_episodes)
        out = {"episodes": self.episode_count,
               "return_mean": float(np.mean([e[0] for e in episodes])) if episodes else None,
               "success_rate": float(np.mean([e[2] for e in episodes])) if episodes else None}
        if self.recent_domain:
            out["mass_scale_min"] = min(m for m, _ in self.recent_domain)
            out["noise_std_max"] = max(n for _, n in self.recent_domain)
        if len(self.objects) > 1:
            out["objects"] = {o: {"episodes": self.object_episodes[o],
                                  "success_rate": float(np.mean(d)) if d else None} for o, d in self.by_object.items()}
        return out

    def stats(self, elapsed: float, updates0: int, ingested0: int) -> dict:
        """Counters, and rates over the ``elapsed`` seconds since ``updates0``/``ingested0``."""
        return {
            "ingested": self.ingested,
            "updates": self.sac.num_updates,
            "updates_per_s": (self.sac.num_updates - updates0) / max(elapsed, 1e-9),
            "update_debt": float(self.updates_due),  # owed for data ingested; the rate limiter bounds it
            "updates_forgone": int(self.updates_forgone),
            "ingest_per_s": (self.ingested - ingested0) / max(elapsed, 1e-9),
            "replay_size": len(self.buffer),
            "policy_version": self.policy_version,
            **self.episode_stats(),
            "alpha": self.sac.alpha,
            "last_checkpoint": self.last_checkpoint,
        }

    def write_scalars(self, writer, values: dict, metrics: dict) -> None:
        """The TensorBoard figures of one stats window (``forcegrasp plot`` reads these tags)."""
        step = self.ingested
        for key in ("updates_per_s", "ingest_per_s", "replay_size", "rejected", "gaps", "alpha"):
            if key in values:
                writer.add_scalar(f"learner/{key}", values[key], step)
        for key in ("return_mean", "success_rate"):
            if values[key] is not None:
                writer.add_scalar(f"actors/{key}_100", values[key], step)
        for key in ("mass_scale_min", "noise_std_max"):  # over the last 200 batches
            if key in values:
                writer.add_scalar(f"actors/{key}", values[key], step)
        for name, v in values.get("objects", {}).items():
            if v["success_rate"] is not None:
                writer.add_scalar(f"actors/{name}/success_rate_100", v["success_rate"], step)
        for k, v in metrics.items():
            writer.add_scalar(f"sac/{k}", v, step)

    # ------------------------------------------------------------------ giving weights and files
    def weights(self) -> Weights:
        """The deployed actor as the next policy version (what every actor loads)."""
        self.policy_version += 1
        return Weights(self.policy_version, self.sac.num_updates, weights_of(self.sac.deployed_actor),
                       meta={"policy_metadata": self.metadata().to_json()})

    def save_policy(self) -> Path:
        """A policy snapshot for the evaluator (~350 KB), far more often than the full checkpoint."""
        policy = self.sac.policy(self.metadata())
        self.files.checkpoints.mkdir(exist_ok=True)
        path = policy.save(self.files.snapshot(self.ingested))
        policy.save(self.files.latest_policy)
        self.last_policy = self.ingested
        return path

    def checkpoint(self) -> Path:
        """Replay and policy first, learner state last: the learner file marks a complete set."""
        if self.config.learner.snapshot_replay:
            self.buffer.save(self.files.replay)
        policy_path = self.save_policy()
        self.sac.save_checkpoint(self.files.checkpoint, extra={"ingested": self.ingested,
                                                                "policy_version": self.policy_version,
                                                                **self.checkpoint_extra()})
        self.last_checkpoint = self.ingested
        return policy_path

    def checkpoint_extra(self) -> dict:
        """More learner state for the checkpoint header (JSON); the service adds its streams."""
        return {}

    def save_due(self) -> Path | None:
        """The file the recipe calls for now, if any: a full checkpoint every
        ``learner.checkpoint_every`` transitions, else a snapshot every ``evaluator.eval_every``."""
        if self.ingested - self.last_checkpoint >= self.config.learner.checkpoint_every:
            return self.checkpoint()
        if self.ingested - self.last_policy >= self.config.evaluator.eval_every:
            return self.save_policy()
        return None
