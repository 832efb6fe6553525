"""The messages services exchange: transitions, weights, stats, checkpoint announcements.

Each ``encode_*`` checks what it sends by decoding it, so a receiver never sees a message its
own sender would refuse; each ``decode_*`` validates every field (see ``wire.py``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from forcegrasp.protocol.wire import (
    DEFAULT_LIMITS, FLAGS, FLOAT32, INT64_MAX, PROTOCOL_VERSION, R_FIELD, R_MISSING, R_OVERSIZE, R_SHAPE, T_CHECKPOINT, T_PROGRESS, T_STATS,
    T_TRANSITIONS, T_WEIGHTS, WEIGHT_DTYPES, Limits, ProtocolError, Reader, check_values, checked, decode_array,
    encode_array, is_int, json_leaf, number_leaf, numbers_to_wire, pack, unpack, validate_name,
)


# --------------------------------------------------------------------------------------------
# TransitionBatch
# --------------------------------------------------------------------------------------------

@dataclass
class TransitionBatch:
    """``n`` consecutive transitions from one actor, with episode stats of episodes that ended.

    ``seq`` counts batches per actor from 0 (gaps reveal loss), ``policy_version`` is the version
    of the weights the actor acted with (learner measures staleness).  Decoded arrays are
    read-only views over the received bytes: copy them into the replay buffer.
    """

    actor_id: str
    seq: int
    policy_version: int
    obs: np.ndarray             # f32[n, obs_dim]
    action: np.ndarray          # f32[n, act_dim]
    reward: np.ndarray          # f32[n]
    next_obs: np.ndarray        # f32[n, obs_dim]
    terminated: np.ndarray      # bool[n]
    truncated: np.ndarray       # bool[n]
    episode_returns: np.ndarray | None = None    # f32[k], episodes finished in this batch
    episode_lengths: np.ndarray | None = None    # i32[k]
    episode_successes: np.ndarray | None = None  # bool[k]
    time: float = field(default_factory=time.time)  # sender wall clock, seconds
    epoch: int = 0  # random per actor process start: tells a restart from a resent batch
    horizon: np.ndarray | None = None          # i32[n] n-step horizon h in [1, MAX_HORIZON]; absent: 1
    privileged: np.ndarray | None = None       # f32[n, p] simulator state for an asymmetric critic
    next_privileged: np.ndarray | None = None  # f32[n, p] the same at next_obs
    objects: list[str] | None = None           # the object names the indices below refer to (1..255, distinct)
    object_index: np.ndarray | None = None     # u8[n] each transition's object, an index into objects
    episode_objects: np.ndarray | None = None  # u8[k] each ended episode's object (with objects and episodes)

    @property
    def n(self) -> int:
        return int(self.reward.shape[0])

    @property
    def has_episodes(self) -> bool:
        return self.episode_returns is not None


def encode_transitions(batch: TransitionBatch, limits: Limits = DEFAULT_LIMITS) -> bytes:
    """Validate and pack a batch with the receiver's rules; casts to the wire dtypes first.

    Producers may pass float64 or int flags.  A batch the learner would reject (NaN from a
    diverged simulation, inconsistent lengths) raises ProtocolError here, at the source.
    """
    wire = _to_wire_dtypes(batch)
    _check_batch_shapes(wire, None, None, limits)
    for name in ("obs", "action", "reward", "next_obs", "episode_returns", "privileged", "next_privileged"):
        if getattr(wire, name) is not None:
            check_values(getattr(wire, name), name)
    _check_extras(wire)
    _check_objects(wire)
    for name in ("seq", "policy_version", "epoch"):
        if not is_int(getattr(wire, name)) or not 0 <= getattr(wire, name) <= INT64_MAX:
            raise ProtocolError(R_FIELD, f"{name} must be an integer in [0, 2^63)")
    msg = {"v": PROTOCOL_VERSION, "t": T_TRANSITIONS, "actor": wire.actor_id, "seq": wire.seq,
           "policy_version": wire.policy_version, "time": wire.time, "epoch": wire.epoch}
    for name in ("obs", "action", "reward", "next_obs", "terminated", "truncated"):
        msg[name] = encode_array(getattr(wire, name))
    for name in ("horizon", "privileged", "next_privileged", "object_index"):
        if getattr(wire, name) is not None:
            msg[name] = encode_array(getattr(wire, name))
    if wire.objects is not None:
        msg["objects"] = list(wire.objects)
    if wire.has_episodes:
        msg["ep_return"] = encode_array(wire.episode_returns)
        msg["ep_length"] = encode_array(wire.episode_lengths)
        msg["ep_success"] = encode_array(wire.episode_successes)
        if wire.episode_objects is not None:
            msg["ep_object"] = encode_array(wire.episode_objects)
    payload = pack(msg)
    if len(payload) > limits.max_payload_bytes:
        raise ProtocolError(R_OVERSIZE, f"{len(payload)} bytes > cap {limits.max_payload_bytes}")
    return payload


def _to_wire_dtypes(b: TransitionBatch) -> TransitionBatch:
    """A copy of the batch whose arrays have the wire dtypes (no copy when they already do)."""
    episodes = (b.episode_returns, b.episode_lengths, b.episode_successes)
    if any(e is not None for e in episodes) and any(e is None for e in episodes):
        raise ProtocolError(R_MISSING, "episode_returns, episode_lengths and episode_successes go together")

    def cast(x: Any, dtype: type) -> np.ndarray | None:
        return None if x is None else np.asarray(x, dtype=dtype)

    return TransitionBatch(
        actor_id=validate_name(b.actor_id, "actor id"), seq=int(b.seq), policy_version=int(b.policy_version),
        time=float(b.time), obs=cast(b.obs, np.float32), action=cast(b.action, np.float32),
        reward=cast(b.reward, np.float32), next_obs=cast(b.next_obs, np.float32),
        terminated=cast(b.terminated, np.bool_), truncated=cast(b.truncated, np.bool_),
        episode_returns=cast(b.episode_returns, np.float32), episode_lengths=cast(b.episode_lengths, np.int32),
        episode_successes=cast(b.episode_successes, np.bool_), epoch=int(b.epoch),
        horizon=cast(b.horizon, np.int32), privileged=cast(b.privileged, np.float32),
        next_privileged=cast(b.next_privileged, np.float32),
        objects=_object_names(None if b.objects is None else list(b.objects)),
        object_index=_index_cast(b.object_index, "object_index"),
        episode_objects=_index_cast(b.episode_objects, "episode_objects"),
    )


def _index_cast(x: Any, name: str) -> np.ndarray | None:
    """Object indices as u8, refusing values a byte cannot hold (a cast would wrap them)."""
    if x is None:
        return None
    a = np.asarray(x)
    if a.size and (a.dtype.kind not in "iu" or a.min() < 0 or a.max() > MAX_OBJECTS - 1):
        raise ProtocolError(R_FIELD, f"{name} must hold integers in [0, {MAX_OBJECTS})")
    return a.astype(np.uint8)


def decode_transitions(payload: Any, *, obs_dim: int | None = None, act_dim: int | None = None,
                       priv_dim: int | None = None, limits: Limits = DEFAULT_LIMITS) -> TransitionBatch:
    """Checked TransitionBatch; ``obs_dim``/``act_dim`` are what the receiver's env expects and
    ``priv_dim`` the privileged-state width its critic expects (0: none may come; None: any)."""
    r = Reader(unpack(payload, limits), T_TRANSITIONS, limits)
    batch = TransitionBatch(
        actor_id=r.name("actor"), seq=r.integer("seq"), policy_version=r.integer("policy_version"),
        time=r.number("time", 0.0), epoch=r.integer("epoch", 0),
        obs=r.array("obs", FLOAT32), action=r.array("action", FLOAT32),
        reward=r.array("reward", FLOAT32), next_obs=r.array("next_obs", FLOAT32),
        terminated=_as_bool(r.array("terminated", FLAGS)), truncated=_as_bool(r.array("truncated", FLAGS)),
        episode_returns=r.array("ep_return", FLOAT32, None),
        episode_lengths=r.array("ep_length", frozenset({"<i4"}), None),
        episode_successes=_as_bool(r.array("ep_success", FLAGS, None)),
        horizon=r.array("horizon", frozenset({"<i4"}), None),
        privileged=r.array("privileged", FLOAT32, None), next_privileged=r.array("next_privileged", FLOAT32, None),
        objects=_object_names(r.raw("objects", None)), object_index=r.array("object_index", U8, None),
        episode_objects=r.array("ep_object", U8, None),
    )
    r.finish()
    _check_batch_shapes(batch, obs_dim, act_dim, limits)
    _check_extras(batch, priv_dim)
    _check_objects(batch)
    return batch


#: At most this many objects per batch (its indices are one byte); names as `validate_name`.
MAX_OBJECTS = 255
U8 = frozenset({"|u1"})


def _object_names(raw: Any) -> list[str] | None:
    if raw is None:
        return None
    if not isinstance(raw, list) or not 1 <= len(raw) <= MAX_OBJECTS:
        raise ProtocolError(R_FIELD, f"objects must be a list of 1..{MAX_OBJECTS} object names")
    names = [validate_name(o, "object name") for o in raw]
    if len(set(names)) != len(names):
        raise ProtocolError(R_FIELD, f"objects names an object twice: {names[:8]}")
    return names


def _check_objects(b: TransitionBatch) -> None:
    """``objects`` and ``object_index`` go together; ``ep_object`` with them and the episode stats;
    every index points into ``objects``."""
    if (b.objects is None) != (b.object_index is None):
        raise ProtocolError(R_MISSING, "objects and object_index go together")
    if b.objects is None:
        if b.episode_objects is not None:
            raise ProtocolError(R_MISSING, "ep_object needs objects")
        return
    if b.has_episodes != (b.episode_objects is not None):
        raise ProtocolError(R_MISSING, "with objects, ep_object comes with the episode stats and only with them")
    pairs = [("object_index", b.object_index, b.n)]
    if b.episode_objects is not None:
        pairs.append(("ep_object", b.episode_objects, b.episode_returns.shape[0]))
    for name, arr, length in pairs:
        if arr.shape != (length,):
            raise ProtocolError(R_SHAPE, f"{name} has shape {list(arr.shape)}, expected [{length}]")
        if arr.size and int(arr.max()) >= len(b.objects):
            raise ProtocolError(R_FIELD, f"{name}: index {int(arr.max())} outside the {len(b.objects)} objects")


#: Longest n-step horizon a transition may declare; bound on privileged-state magnitudes (cm within
#: the palm and object tolerances, 0/1 flags: the MDP cannot produce larger values).
MAX_HORIZON = 64
MAX_PRIVILEGED_ABS = 100.0


def _check_extras(b: TransitionBatch, priv_dim: int | None = None) -> None:
    """n-step horizons and privileged critic state: optional fields, checked like the rest."""
    n = b.n
    if b.horizon is not None:
        if b.horizon.shape != (n,):
            raise ProtocolError(R_SHAPE, f"horizon has shape {list(b.horizon.shape)}, expected [{n}]")
        if n and (b.horizon.min() < 1 or b.horizon.max() > MAX_HORIZON):
            raise ProtocolError(R_FIELD, f"horizon values must lie in [1, {MAX_HORIZON}]")
    pair = (b.privileged, b.next_privileged)
    if (pair[0] is None) != (pair[1] is None):
        raise ProtocolError(R_MISSING, "privileged and next_privileged go together")
    if pair[0] is None:
        if priv_dim:
            raise ProtocolError(R_MISSING, f"this learner's critic needs {priv_dim} privileged values per transition")
        return
    want = pair[0].shape[-1] if priv_dim is None and pair[0].ndim == 2 else priv_dim
    for name, arr in zip(("privileged", "next_privileged"), pair):
        if arr.shape != (n, want):
            raise ProtocolError(R_SHAPE, f"{name} has shape {list(arr.shape)}, expected {[n, want]}")
        if arr.size and np.abs(arr).max() > MAX_PRIVILEGED_ABS:
            raise ProtocolError(R_FIELD, f"{name}: values beyond +-{MAX_PRIVILEGED_ABS}")


def _as_bool(a: np.ndarray | None) -> np.ndarray | None:
    """Flags may arrive as |u1 (languages without a bool dtype): only 0/1 are accepted."""
    if a is None or a.dtype == np.bool_:
        return a
    if a.size and a.max() > 1:
        raise ProtocolError(R_FIELD, "flag arrays hold only 0 or 1")
    return a.view(np.bool_)


def _check_batch_shapes(b: TransitionBatch, obs_dim: int | None, act_dim: int | None, limits: Limits) -> None:
    if b.reward.ndim != 1:
        raise ProtocolError(R_SHAPE, f"reward must be 1-D, got shape {list(b.reward.shape)}")
    n = b.n
    if not 1 <= n <= limits.max_batch:
        raise ProtocolError(R_SHAPE, f"batch of {n} transitions outside [1, {limits.max_batch}]")
    obs_dim = b.obs.shape[-1] if obs_dim is None and b.obs.ndim == 2 else obs_dim
    act_dim = b.action.shape[-1] if act_dim is None and b.action.ndim == 2 else act_dim
    expected = {"obs": (n, obs_dim), "next_obs": (n, obs_dim), "action": (n, act_dim),
                "terminated": (n,), "truncated": (n,)}
    for name, shape in expected.items():
        got = getattr(b, name).shape
        if got != shape:
            raise ProtocolError(R_SHAPE, f"{name} has shape {list(got)}, expected {list(shape)}")
    episodes = (b.episode_returns, b.episode_lengths, b.episode_successes)
    if all(e is None for e in episodes):
        return
    if any(e is None for e in episodes):
        raise ProtocolError(R_MISSING, "ep_return, ep_length and ep_success go together")
    k = b.episode_returns.shape[0] if b.episode_returns.ndim == 1 else -1
    if not 0 <= k <= n or any(e.shape != (k,) for e in episodes):
        raise ProtocolError(R_SHAPE, f"episode stats must be three 1-D arrays of equal length <= {n}")


# --------------------------------------------------------------------------------------------
# Weights
# --------------------------------------------------------------------------------------------

@dataclass
class Weights:
    """Policy parameters broadcast by the learner (and returned by ``weights/latest``).

    ``policy_version`` increases with every broadcast; ``step`` is the learner's update counter.
    ``meta`` is small JSON-able data (e.g. architecture, obs normalisation, env name).
    """

    policy_version: int
    step: int
    params: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)
    time: float = field(default_factory=time.time)


def encode_weights(w: Weights, limits: Limits = DEFAULT_LIMITS) -> bytes:
    msg = {
        "v": PROTOCOL_VERSION, "t": T_WEIGHTS, "policy_version": int(w.policy_version),
        "step": int(w.step), "time": float(w.time),
        "params": {str(k): encode_array(v) for k, v in w.params.items()}, "meta": w.meta,
    }
    return checked(msg, decode_weights, limits)


def decode_weights(payload: Any, *, expected: Mapping[str, tuple[int, ...]] | None = None,
                   limits: Limits = DEFAULT_LIMITS) -> Weights:
    """Checked Weights; ``expected`` (name -> shape) rejects a policy of another architecture."""
    r = Reader(unpack(payload, limits), T_WEIGHTS, limits)
    version, step, sent = r.integer("policy_version"), r.integer("step"), r.number("time", 0.0)
    raw = r.raw("params")
    if not isinstance(raw, dict) or not raw:
        raise ProtocolError(R_FIELD, "params must be a non-empty map of name -> array")
    params = {}
    for name, spec in raw.items():
        if not isinstance(name, str) or not 0 < len(name) <= 256:
            raise ProtocolError(R_FIELD, "param names must be strings of 1..256 chars")
        params[name] = decode_array(spec, f"params.{name}", WEIGHT_DTYPES, limits)
    meta = r.tree("meta", json_leaf, "JSON data", {}, lists=True)
    r.finish()
    if expected is not None:
        _check_expected_params(params, expected)
    return Weights(policy_version=version, step=step, params=params, meta=meta, time=sent)


def _check_expected_params(params: Mapping[str, np.ndarray], expected: Mapping[str, tuple[int, ...]]) -> None:
    if set(params) != set(expected):
        missing, extra = sorted(set(expected) - set(params)), sorted(set(params) - set(expected))
        raise ProtocolError(R_SHAPE, f"params differ: missing {missing[:5]}, unexpected {extra[:5]}")
    for name, shape in expected.items():
        if tuple(params[name].shape) != tuple(shape):
            raise ProtocolError(R_SHAPE, f"params.{name} has shape {list(params[name].shape)}, expected {list(shape)}")


# --------------------------------------------------------------------------------------------
# Stats and checkpoint announcements
# --------------------------------------------------------------------------------------------

@dataclass
class Stats:
    """Free-form numbers a service publishes for dashboards (nested maps allowed)."""

    service: str
    id: str
    values: dict[str, Any]
    time: float = field(default_factory=time.time)


def encode_stats(s: Stats, limits: Limits = DEFAULT_LIMITS) -> bytes:
    msg = {"v": PROTOCOL_VERSION, "t": T_STATS, "service": validate_name(s.service, "service"),
           "id": validate_name(s.id, "id"), "time": float(s.time), "values": numbers_to_wire(s.values)}
    return checked(msg, decode_stats, limits)


def decode_stats(payload: Any, *, limits: Limits = DEFAULT_LIMITS) -> Stats:
    r = Reader(unpack(payload, limits), T_STATS, limits)
    stats = Stats(service=r.name("service"), id=r.name("id"), time=r.number("time", 0.0),
                  values=r.tree("values", number_leaf, "a number or null"))
    r.finish()
    return stats


@dataclass
class Checkpoint:
    """A checkpoint file on disk: learner announcements and the evaluator's ``best`` reply.

    ``metrics`` holds numbers such as the evaluation return or success rate (``None`` = unknown).
    """

    step: int
    path: str
    policy_version: int = 0
    metrics: dict[str, Any] = field(default_factory=dict)
    time: float = field(default_factory=time.time)


def encode_checkpoint(c: Checkpoint, limits: Limits = DEFAULT_LIMITS) -> bytes:
    msg = {"v": PROTOCOL_VERSION, "t": T_CHECKPOINT, "step": int(c.step), "path": str(c.path),
           "policy_version": int(c.policy_version), "time": float(c.time),
           "metrics": numbers_to_wire(c.metrics)}
    return checked(msg, decode_checkpoint, limits)


def decode_checkpoint(payload: Any, *, limits: Limits = DEFAULT_LIMITS) -> Checkpoint:
    r = Reader(unpack(payload, limits), T_CHECKPOINT, limits)
    ckpt = Checkpoint(step=r.integer("step"), path=r.text("path"), policy_version=r.integer("policy_version", 0),
                      time=r.number("time", 0.0), metrics=r.tree("metrics", number_leaf, "a number or null", {}))
    if not ckpt.path:
        raise ProtocolError(R_FIELD, "path is empty")
    r.finish()
    return ckpt


# --------------------------------------------------------------------------------------------
# Progress: the learner's flow control and acknowledgements
# --------------------------------------------------------------------------------------------

@dataclass
class Progress:
    """The learner's word to the actors, ~20 times a second (``forcegrasp/<run>/progress``).

    ``headroom``: transitions it still takes before it owes too many updates (actors pause at
    0 or below; ``None``: no limit). ``acked``: per actor, the ``(epoch, seq)`` of the last batch
    ingested from its current process, so the actor can forget what is safely in replay.
    """

    ingested: int
    updates: int
    headroom: float | None
    acked: dict[str, tuple[int, int]] = field(default_factory=dict)
    time: float = field(default_factory=time.time)


def encode_progress(p: Progress, limits: Limits = DEFAULT_LIMITS) -> bytes:
    msg = {"v": PROTOCOL_VERSION, "t": T_PROGRESS, "ingested": int(p.ingested), "updates": int(p.updates),
           "headroom": None if p.headroom is None else float(p.headroom), "time": float(p.time),
           "acked": {validate_name(a, "actor id"): [int(e), int(s)] for a, (e, s) in p.acked.items()}}
    return checked(msg, decode_progress, limits)


def decode_progress(payload: Any, *, limits: Limits = DEFAULT_LIMITS) -> Progress:
    r = Reader(unpack(payload, limits), T_PROGRESS, limits)
    headroom = r.raw("headroom")
    if headroom is not None:
        headroom = r.number("headroom")
    acked_raw = r.raw("acked")
    if not isinstance(acked_raw, dict):
        raise ProtocolError(R_FIELD, "acked must be a map of actor id -> [epoch, seq]")
    acked = {}
    for actor, pair in acked_raw.items():
        if (not isinstance(pair, list) or len(pair) != 2 or not all(is_int(x) for x in pair)
                or not all(-1 <= x <= INT64_MAX for x in pair)):
            raise ProtocolError(R_FIELD, f"acked[{actor!r}] must be [epoch, seq] integers")
        acked[validate_name(actor, "actor id")] = (pair[0], pair[1])
    p = Progress(ingested=r.integer("ingested"), updates=r.integer("updates"), headroom=headroom, acked=acked,
                 time=r.number("time", 0.0))
    r.finish()
    return p
