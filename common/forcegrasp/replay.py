"""Replay buffer: a preallocated numpy ring of transitions with uniform sampling and disk snapshots.

Transitions arrive in batches (an actor ships many steps per message), so inserts are vectorised:
one or two slice copies per field whatever the batch size, no per-transition Python. Snapshots are
a standard uncompressed ``.npz`` (a zip of ``.npy`` arrays plus a JSON header member), written
atomically; reading uses ``allow_pickle=False`` and the zip CRC-32 of every member, so a damaged
snapshot is reported instead of silently resuming from garbage.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from forcegrasp.policy_file import atomic_write

SNAPSHOT_FORMAT = "forcegrasp-replay"
SNAPSHOT_VERSION = 2
READABLE_VERSIONS = (1, 2)  # version 1 had neither horizons nor privileged state
FIELDS = ("obs", "action", "reward", "next_obs", "terminated", "horizon")
PRIVILEGED_FIELDS = ("privileged", "next_privileged")


class ReplaySnapshotError(ValueError):
    """A replay snapshot that cannot be loaded, with the reason in the message."""


@dataclass
class Batch:
    """A sampled minibatch; `terminated` is 1.0 where the episode truly ended (no bootstrap)."""

    obs: np.ndarray  # (B, obs_dim) float32
    action: np.ndarray  # (B, act_dim) float32
    reward: np.ndarray  # (B,) float32
    next_obs: np.ndarray  # (B, obs_dim) float32
    terminated: np.ndarray  # (B,) float32
    horizon: np.ndarray | None = None  # (B,) float32 n-step horizon h: bootstrap with gamma^h (None: 1)
    privileged: np.ndarray | None = None  # (B, priv_dim) float32, for an asymmetric critic
    next_privileged: np.ndarray | None = None


class ReplayBuffer:
    """Fixed-capacity FIFO ring of (obs, action, reward, next_obs, terminated, horizon) and, with
    ``priv_dim > 0``, the privileged state at obs and next_obs; all float32."""

    def __init__(self, obs_dim: int, act_dim: int, capacity: int = 1_000_000, priv_dim: int = 0):
        if capacity <= 0:
            raise ValueError("capacity must be positive")
        self.obs_dim, self.act_dim, self.capacity = int(obs_dim), int(act_dim), int(capacity)
        self.priv_dim = int(priv_dim)
        self.fields = FIELDS + (PRIVILEGED_FIELDS if self.priv_dim else ())
        # np.zeros maps pages lazily: a 1 M buffer costs memory only as it fills.
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.action = np.zeros((capacity, act_dim), np.float32)
        self.reward = np.zeros((capacity,), np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.terminated = np.zeros((capacity,), np.float32)
        self.horizon = np.ones((capacity,), np.float32)
        if self.priv_dim:
            self.privileged = np.zeros((capacity, self.priv_dim), np.float32)
            self.next_privileged = np.zeros((capacity, self.priv_dim), np.float32)
        self.pos = 0  # next slot to write
        self.size = 0  # number of valid slots
        self.total_added = 0  # transitions ever inserted (for logging / resuming counters)

    def __len__(self) -> int:
        return self.size

    def add(self, obs, action, reward, next_obs, terminated) -> None:
        """Insert a single transition."""
        self.add_batch(np.asarray(obs)[None], np.asarray(action)[None], np.asarray([reward]),
                       np.asarray(next_obs)[None], np.asarray([terminated]))

    def add_batch(self, obs, action, reward, next_obs, terminated, horizon=None, privileged=None,
                  next_privileged=None) -> None:
        """Insert n transitions (arrays with leading dimension n), overwriting the oldest on wrap.
        ``horizon`` defaults to one step; the privileged pair is required exactly when ``priv_dim``."""
        n = len(np.asarray(reward))
        data = {"obs": obs, "action": action, "reward": reward, "next_obs": next_obs, "terminated": terminated,
                "horizon": np.ones(n) if horizon is None else horizon}
        if self.priv_dim:
            if privileged is None or next_privileged is None:
                raise ValueError(f"add_batch: this buffer keeps {self.priv_dim} privileged values per transition")
            data.update(privileged=privileged, next_privileged=next_privileged)
        data = {k: np.asarray(v, dtype=np.float32) for k, v in data.items()}
        for k, v in data.items():
            want = (n, *getattr(self, k).shape[1:])
            if v.shape != want:
                raise ValueError(f"add_batch: {k} has shape {v.shape}, expected {want}")
        self.total_added += n
        if n > self.capacity:  # only the newest `capacity` rows can survive
            data = {k: v[-self.capacity :] for k, v in data.items()}
            n = self.capacity
        first = min(n, self.capacity - self.pos)  # rows before the end of the ring
        for k, v in data.items():
            dst = getattr(self, k)
            dst[self.pos : self.pos + first] = v[:first]
            dst[: n - first] = v[first:]
        self.pos = (self.pos + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        """Uniform sample (with replacement) over the slots written so far."""
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        idx = rng.integers(0, self.size, size=batch_size)
        priv = (self.privileged[idx], self.next_privileged[idx]) if self.priv_dim else (None, None)
        return Batch(self.obs[idx], self.action[idx], self.reward[idx], self.next_obs[idx], self.terminated[idx],
                     self.horizon[idx], *priv)

    # -- snapshots ------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Write the valid part of the ring atomically (old snapshot survives a crash mid-write)."""
        header = {
            "format": SNAPSHOT_FORMAT, "version": SNAPSHOT_VERSION, "obs_dim": self.obs_dim,
            "act_dim": self.act_dim, "capacity": self.capacity, "pos": self.pos, "size": self.size,
            "total_added": self.total_added, "priv_dim": self.priv_dim,
        }
        arrays = {k: getattr(self, k)[: self.size] for k in self.fields}
        arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
        with atomic_write(path) as f:
            np.savez(f, **arrays)
        return Path(path)

    @classmethod
    def load(cls, path: str | os.PathLike, capacity: int | None = None) -> "ReplayBuffer":
        """Rebuild a buffer from a snapshot; `capacity` may enlarge it (oldest-first order kept)."""
        try:
            with np.load(path, allow_pickle=False) as z:
                if "header" not in z.files:
                    raise ReplaySnapshotError(f"{path}: not a ForceGrasp replay snapshot (no header)")
                header = json.loads(z["header"].tobytes())
                if header.get("format") != SNAPSHOT_FORMAT or header.get("version") not in READABLE_VERSIONS:
                    raise ReplaySnapshotError(
                        f"{path}: unsupported snapshot format {header.get('format')!r} version {header.get('version')!r} "
                        f"(this ForceGrasp reads {SNAPSHOT_FORMAT!r} version {SNAPSHOT_VERSION})"
                    )
                priv_dim = int(header.get("priv_dim", 0) or 0)
                names = FIELDS + (PRIVILEGED_FIELDS if priv_dim else ())
                arrays = {k: z[k] for k in names if k != "horizon" or header.get("version") != 1}
        except ReplaySnapshotError:
            raise
        except FileNotFoundError:
            raise
        except (zipfile.BadZipFile, ValueError, KeyError, OSError, EOFError) as exc:
            raise ReplaySnapshotError(f"{path}: corrupt or truncated replay snapshot ({type(exc).__name__}: {exc})") from None
        try:
            size, pos, old_capacity = int(header["size"]), int(header["pos"]), int(header["capacity"])
            obs_dim, act_dim, total_added = int(header["obs_dim"]), int(header["act_dim"]), int(header["total_added"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ReplaySnapshotError(f"{path}: replay snapshot header is incomplete ({exc!r})") from None
        arrays.setdefault("horizon", np.ones(size, np.float32))
        shapes = {"obs": (size, obs_dim), "action": (size, act_dim), "reward": (size,),
                  "next_obs": (size, obs_dim), "terminated": (size,), "horizon": (size,)}
        if priv_dim:
            shapes.update(privileged=(size, priv_dim), next_privileged=(size, priv_dim))
        for k, shape in shapes.items():
            if arrays[k].shape != shape or arrays[k].dtype != np.float32:
                raise ReplaySnapshotError(
                    f"{path}: field {k!r} is {arrays[k].dtype}{arrays[k].shape}, header says float32{shape}"
                )
        if not (0 <= pos < old_capacity and size <= old_capacity and (pos == size % old_capacity or size == old_capacity)):
            raise ReplaySnapshotError(f"{path}: inconsistent ring position (pos {pos}, size {size}, capacity {old_capacity})")
        buf = cls(obs_dim, act_dim, capacity or old_capacity, priv_dim=priv_dim)
        if buf.capacity == old_capacity:  # same ring: copy slots as they were
            for k in buf.fields:
                getattr(buf, k)[:size] = arrays[k]
            buf.pos, buf.size = pos, size
        else:  # re-insert oldest first so FIFO eviction order survives the change of capacity
            order = np.r_[pos:size, 0:pos] if size == old_capacity else np.arange(size)
            buf.add_batch(**{k: arrays[k][order] for k in buf.fields})
        buf.total_added = total_added
        return buf
