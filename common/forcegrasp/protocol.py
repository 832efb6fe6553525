"""ForceGrasp wire protocol: Zenoh key expressions and msgpack messages.

Every service (and any third-party client, see ``docs/protocol.md``) talks through the keys built
by :class:`Keys` and the four message types below.  Messages are msgpack maps carrying a protocol
version ``v`` and a type tag ``t``; numeric arrays travel as raw little-endian bytes with their
dtype and shape, so a batch of transitions costs one memory copy to encode and none to decode.

Receivers are never trusted: every ``decode_*`` function checks the size, msgpack limits, version,
type, field types, array dtypes (whitelist), shapes and finiteness, and raises exactly one
exception type, :class:`ProtocolError`, whose ``reason`` is a short category that services count
with :class:`RejectCounter` before dropping the message.  Nothing here ever unpickles.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import msgpack
import numpy as np

PROTOCOL_VERSION = 1
ROOT = "forcegrasp"

# Message type tags (the ``t`` field).
T_TRANSITIONS = "transitions"
T_WEIGHTS = "weights"
T_STATS = "stats"
T_CHECKPOINT = "checkpoint"

# Reasons carried by ProtocolError.reason: small and fixed, so counters stay readable.
R_OVERSIZE = "oversize"
R_MALFORMED = "malformed"
R_NOT_A_MAP = "not_a_map"
R_VERSION = "version"
R_TYPE = "type"
R_MISSING = "missing_field"
R_EXTRA = "extra_field"
R_FIELD = "bad_field"
R_DTYPE = "dtype"
R_SHAPE = "shape"
R_NONFINITE = "nonfinite"
REASONS = (R_OVERSIZE, R_MALFORMED, R_NOT_A_MAP, R_VERSION, R_TYPE, R_MISSING, R_EXTRA,
           R_FIELD, R_DTYPE, R_SHAPE, R_NONFINITE)

#: Every dtype the protocol can carry; each field narrows this further.
ALLOWED_DTYPES = frozenset({"<f2", "<f4", "<f8", "<i4", "<i8", "|u1", "|b1"})
FLOAT32 = frozenset({"<f4"})
FLAGS = frozenset({"|b1", "|u1"})
WEIGHT_DTYPES = ALLOWED_DTYPES
_NP_DTYPES = {name: np.dtype(name) for name in ALLOWED_DTYPES}

_INT64_MAX = 2**63 - 1
_FORBIDDEN_NAME_CHARS = frozenset("*$/#?")
_MAX_NAME_LEN = 128


class ProtocolError(ValueError):
    """A message (or a name) broke the protocol.  ``reason`` is one of :data:`REASONS`."""

    def __init__(self, reason: str, detail: str = "") -> None:
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}" if detail else reason)


# --------------------------------------------------------------------------------------------
# Key expressions
# --------------------------------------------------------------------------------------------

def validate_name(name: Any, what: str = "name") -> str:
    """Return ``name`` as a string usable as one key-expression chunk, or raise ProtocolError.

    Run names, actor ids and service names become single chunks of Zenoh keys; a '/', a wildcard
    ('*', '$') or a selector character ('?', '#') inside one would silently widen or break
    subscriptions, so they are refused here instead.  Integers are accepted (actor 3 -> "3").
    """
    if isinstance(name, (bool, np.bool_)) or not isinstance(name, (str, int, np.integer)):
        raise ProtocolError(R_FIELD, f"{what} must be a string, got {type(name).__name__}")
    text = str(name) if isinstance(name, str) else str(int(name))
    if not text:
        raise ProtocolError(R_FIELD, f"{what} is empty")
    if len(text) > _MAX_NAME_LEN:
        raise ProtocolError(R_FIELD, f"{what} longer than {_MAX_NAME_LEN} characters")
    bad = sorted({c for c in text if c in _FORBIDDEN_NAME_CHARS or not c.isprintable() or c.isspace()})
    if bad:
        raise ProtocolError(R_FIELD, f"{what} {text!r} contains forbidden characters {bad!r}")
    return text


class Keys:
    """All key expressions of one training run: ``forcegrasp/<run>/...``.

    One object per run keeps every service on the same spelling; the wildcard forms
    (``all_*``) are what the learner and monitors subscribe to.
    """

    def __init__(self, run: str) -> None:
        self.run = validate_name(run, "run name")
        self.prefix = f"{ROOT}/{self.run}"

    def transitions(self, actor_id: str | int) -> str:
        """Where one actor publishes its TransitionBatch messages."""
        return f"{self.prefix}/transitions/{validate_name(actor_id, 'actor id')}"

    @property
    def all_transitions(self) -> str:
        return f"{self.prefix}/transitions/*"

    @property
    def weights(self) -> str:
        """Learner broadcasts Weights here every N updates."""
        return f"{self.prefix}/weights"

    @property
    def weights_latest(self) -> str:
        """Learner's queryable answering with the current Weights (late joiners ask here)."""
        return f"{self.prefix}/weights/latest"

    @property
    def checkpoints(self) -> str:
        """Learner announces each written checkpoint (Checkpoint message)."""
        return f"{self.prefix}/checkpoints"

    @property
    def progress(self) -> str:
        """Learner's ingestion headroom (Stats message, ~20 Hz): actors pause while it is used up,
        which holds the update-to-data ratio (the rate limiter)."""
        return f"{self.prefix}/progress"

    @property
    def best(self) -> str:
        """Evaluator's queryable answering with its best policy (Checkpoint message)."""
        return f"{self.prefix}/best"

    def stats(self, service: str, instance: str | int) -> str:
        return f"{self.prefix}/stats/{validate_name(service, 'service')}/{validate_name(instance, 'id')}"

    @property
    def all_stats(self) -> str:
        return f"{self.prefix}/stats/**"

    def alive(self, service: str, instance: str | int) -> str:
        """Liveliness token key of one service instance."""
        return f"{self.prefix}/alive/{validate_name(service, 'service')}/{validate_name(instance, 'id')}"

    def alive_of(self, service: str) -> str:
        return f"{self.prefix}/alive/{validate_name(service, 'service')}/*"

    @property
    def all_alive(self) -> str:
        return f"{self.prefix}/alive/**"

    def parse_alive(self, key: str) -> tuple[str, str]:
        """``(service, id)`` of a liveliness key of this run; ProtocolError otherwise."""
        return self._parse_two(str(key), "alive")

    def parse_stats(self, key: str) -> tuple[str, str]:
        return self._parse_two(str(key), "stats")

    def actor_of(self, key: str) -> str:
        """Actor id from a transitions key, so a receiver can check it against the payload."""
        head = f"{self.prefix}/transitions/"
        key = str(key)
        if not key.startswith(head):
            raise ProtocolError(R_FIELD, f"{key!r} is not a transitions key of run {self.run!r}")
        return validate_name(key[len(head):], "actor id")

    def _parse_two(self, key: str, kind: str) -> tuple[str, str]:
        head = f"{self.prefix}/{kind}/"
        parts = key[len(head):].split("/") if key.startswith(head) else []
        if len(parts) != 2:
            raise ProtocolError(R_FIELD, f"{key!r} is not a {kind} key of run {self.run!r}")
        return validate_name(parts[0], "service"), validate_name(parts[1], "id")


# --------------------------------------------------------------------------------------------
# Limits and low-level decoding
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Limits:
    """Bounds applied while decoding; generous for real traffic, tight against junk."""

    max_payload_bytes: int = 64 * 1024 * 1024
    max_str_len: int = 64 * 1024
    max_container_len: int = 4096      # msgpack arrays and maps (shapes, param dicts, metadata)
    max_depth: int = 16                # nesting of free-form metadata / stats
    max_batch: int = 65536             # transitions per TransitionBatch
    max_ndim: int = 8
    allow_extra_fields: bool = False   # unknown top-level fields: reject (default) or ignore


DEFAULT_LIMITS = Limits()


def _unpack(payload: Any, limits: Limits) -> dict:
    """Turn raw bytes into exactly one msgpack map, within the limits, or raise ProtocolError."""
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise ProtocolError(R_MALFORMED, f"payload is {type(payload).__name__}, not bytes")
    size = len(payload)
    if size > limits.max_payload_bytes:
        raise ProtocolError(R_OVERSIZE, f"{size} bytes > cap {limits.max_payload_bytes}")
    if size == 0:
        raise ProtocolError(R_MALFORMED, "empty payload")
    unpacker = msgpack.Unpacker(
        raw=False, strict_map_key=True, use_list=True, max_buffer_size=size,
        max_bin_len=limits.max_payload_bytes, max_str_len=limits.max_str_len,
        max_array_len=limits.max_container_len, max_map_len=limits.max_container_len,
        max_ext_len=0,
    )
    try:
        unpacker.feed(payload)
        obj = unpacker.unpack()
    except msgpack.OutOfData:
        raise ProtocolError(R_MALFORMED, "truncated msgpack") from None
    except Exception as exc:  # msgpack raises ValueError, StackError, FormatError, UnicodeError…
        raise ProtocolError(R_MALFORMED, f"msgpack: {type(exc).__name__} {exc}"[:200]) from None
    if unpacker.tell() != size:
        raise ProtocolError(R_MALFORMED, f"{size - unpacker.tell()} trailing bytes")
    if not isinstance(obj, dict):
        raise ProtocolError(R_NOT_A_MAP, f"top level is {type(obj).__name__}")
    return obj


def _pack(obj: dict) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


# --------------------------------------------------------------------------------------------
# Arrays
# --------------------------------------------------------------------------------------------

def encode_array(x: Any, dtype: Any = None) -> dict:
    """``{"dtype", "shape", "data"}`` for an array: contiguous little-endian raw bytes."""
    a = np.asarray(x) if dtype is None else np.asarray(x, dtype=dtype)
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    if a.dtype.str not in ALLOWED_DTYPES:
        raise ProtocolError(R_DTYPE, f"dtype {a.dtype.str} cannot travel (allowed {sorted(ALLOWED_DTYPES)})")
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": np.ascontiguousarray(a).tobytes()}


def decode_array(spec: Any, name: str, dtypes: frozenset, limits: Limits = DEFAULT_LIMITS) -> np.ndarray:
    """Read-only array view over ``spec["data"]`` after checking dtype, shape, length, values."""
    if not isinstance(spec, dict) or set(spec) != {"dtype", "shape", "data"}:
        raise ProtocolError(R_FIELD, f"{name}: array must be a map with exactly dtype, shape, data")
    dtype, shape, data = spec["dtype"], spec["shape"], spec["data"]
    if not isinstance(dtype, str) or dtype not in dtypes:
        raise ProtocolError(R_DTYPE, f"{name}: dtype {dtype!r} not in {sorted(dtypes)}")
    if (not isinstance(shape, list) or len(shape) > limits.max_ndim
            or not all(_is_int(d) and d >= 0 for d in shape)):
        raise ProtocolError(R_SHAPE, f"{name}: shape must be a list of <= {limits.max_ndim} non-negative ints")
    if not isinstance(data, bytes):
        raise ProtocolError(R_FIELD, f"{name}: data must be msgpack bin, got {type(data).__name__}")
    np_dtype = _NP_DTYPES.get(dtype) or np.dtype(dtype)
    expected = math.prod(shape) * np_dtype.itemsize
    if expected != len(data):
        raise ProtocolError(R_SHAPE, f"{name}: {len(data)} data bytes, shape {shape} of {dtype} needs {expected}")
    arr = np.frombuffer(data, dtype=np_dtype).reshape(shape)
    _check_values(arr, name)
    return arr


def _check_values(arr: np.ndarray, name: str) -> None:
    """Floats must be finite; booleans must be 0/1 bytes (anything else is undefined in numpy)."""
    if arr.dtype.kind == "f" and arr.size and not np.isfinite(arr).all():
        raise ProtocolError(R_NONFINITE, f"{name}: contains NaN or infinity")
    if arr.dtype.kind == "b" and arr.size and arr.view(np.uint8).max() > 1:
        raise ProtocolError(R_FIELD, f"{name}: boolean bytes other than 0/1")


# --------------------------------------------------------------------------------------------
# Field reader shared by all message types
# --------------------------------------------------------------------------------------------

_REQUIRED = object()


class _Reader:
    """Pulls typed fields out of a decoded map and remembers which ones were used."""

    def __init__(self, obj: dict, mtype: str, limits: Limits) -> None:
        version = obj.get("v")
        if not _is_int(version) or version != PROTOCOL_VERSION:
            raise ProtocolError(R_VERSION, f"v={version!r}, this side speaks {PROTOCOL_VERSION}")
        if obj.get("t") != mtype:
            raise ProtocolError(R_TYPE, f"t={obj.get('t')!r}, expected {mtype!r}")
        self.obj, self.limits, self.used = obj, limits, {"v", "t"}

    def _get(self, name: str, default: Any) -> Any:
        self.used.add(name)
        if name in self.obj:
            return self.obj[name]
        if default is _REQUIRED:
            raise ProtocolError(R_MISSING, f"field {name!r} is required")
        return default

    def integer(self, name: str, default: Any = _REQUIRED) -> int:
        value = self._get(name, default)
        if not _is_int(value) or not 0 <= value <= _INT64_MAX:
            raise ProtocolError(R_FIELD, f"{name} must be an integer in [0, 2^63), got {value!r}")
        return value

    def number(self, name: str, default: Any = _REQUIRED) -> float:
        value = self._get(name, default)
        if not _is_number(value) or not math.isfinite(value):
            raise ProtocolError(R_FIELD, f"{name} must be a finite number, got {value!r}")
        return float(value)

    def text(self, name: str, default: Any = _REQUIRED, max_len: int = 4096) -> str:
        value = self._get(name, default)
        if not isinstance(value, str) or len(value) > max_len:
            raise ProtocolError(R_FIELD, f"{name} must be a string of <= {max_len} chars")
        return value

    def name(self, name: str) -> str:
        return validate_name(self._get(name, _REQUIRED), name)

    def raw(self, name: str, default: Any = _REQUIRED) -> Any:
        return self._get(name, default)

    def array(self, name: str, dtypes: frozenset, default: Any = _REQUIRED) -> np.ndarray | None:
        spec = self._get(name, default)
        if spec is None and default is _REQUIRED:  # nil sent for a required array (found by fuzzing)
            raise ProtocolError(R_FIELD, f"field {name!r} must be an array, got nil")
        return None if spec is None else decode_array(spec, name, dtypes, self.limits)

    def tree(self, name: str, leaf: Callable[[Any], bool], what: str, default: Any = _REQUIRED,
             lists: bool = False) -> dict:
        """A free-form string-keyed map whose leaves satisfy ``leaf`` (lists only if ``lists``)."""
        value = self._get(name, default)
        if not isinstance(value, dict):
            raise ProtocolError(R_FIELD, f"{name} must be a map")
        _check_tree(value, leaf, what, name, self.limits.max_depth, lists)
        return value

    def finish(self) -> None:
        extra = set(self.obj) - self.used
        if extra and not self.limits.allow_extra_fields:
            shown = sorted(map(repr, extra))[:5]
            raise ProtocolError(R_EXTRA, f"unknown fields {', '.join(shown)}")


def _check_tree(value: Any, leaf: Callable[[Any], bool], what: str, path: str, depth: int,
                lists: bool) -> None:
    """Bounded-depth walk of a free-form structure: string-keyed maps, optional lists, leaves."""
    if depth < 0:
        raise ProtocolError(R_FIELD, f"{path}: nested deeper than the limit")
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise ProtocolError(R_FIELD, f"{path}: map keys must be strings")
            _check_tree(item, leaf, what, f"{path}.{key}", depth - 1, lists)
    elif isinstance(value, list) and lists:
        for i, item in enumerate(value):
            _check_tree(item, leaf, what, f"{path}[{i}]", depth - 1, lists)
    elif not leaf(value):
        reason = R_NONFINITE if isinstance(value, float) else R_FIELD
        raise ProtocolError(reason, f"{path}: {value!r}"[:120] + f" is not {what}")


def _json_leaf(x: Any) -> bool:
    """JSON scalars with finite floats (the metadata of Weights)."""
    return x is None or isinstance(x, (bool, int, str)) or (isinstance(x, float) and math.isfinite(x))


def _number_leaf(x: Any) -> bool:
    """Numbers for stats and metrics; ``None`` stands for "no value" (encoders map NaN to it)."""
    return x is None or isinstance(x, bool) or _is_int(x) or (isinstance(x, float) and math.isfinite(x))


def _numbers_to_wire(values: Mapping[str, Any], depth: int = DEFAULT_LIMITS.max_depth) -> dict:
    """Plain Python numbers for a stats tree: numpy scalars unwrapped, NaN/inf sent as ``None``."""
    if depth < 0:
        raise ProtocolError(R_FIELD, "stats nested too deep")
    out: dict = {}
    for key, value in values.items():
        if isinstance(value, Mapping):
            out[str(key)] = _numbers_to_wire(value, depth - 1)
            continue
        if isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, float) and not math.isfinite(value):
            value = None
        if not _number_leaf(value):
            raise ProtocolError(R_FIELD, f"stats value {key!r}={value!r} is not a number")
        out[str(key)] = value
    return out


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
            _check_values(getattr(wire, name), name)
    _check_extras(wire)
    for name in ("seq", "policy_version", "epoch"):
        if not _is_int(getattr(wire, name)) or not 0 <= getattr(wire, name) <= _INT64_MAX:
            raise ProtocolError(R_FIELD, f"{name} must be an integer in [0, 2^63)")
    msg = {"v": PROTOCOL_VERSION, "t": T_TRANSITIONS, "actor": wire.actor_id, "seq": wire.seq,
           "policy_version": wire.policy_version, "time": wire.time, "epoch": wire.epoch}
    for name in ("obs", "action", "reward", "next_obs", "terminated", "truncated"):
        msg[name] = encode_array(getattr(wire, name))
    for name in ("horizon", "privileged", "next_privileged"):
        if getattr(wire, name) is not None:
            msg[name] = encode_array(getattr(wire, name))
    if wire.has_episodes:
        msg["ep_return"] = encode_array(wire.episode_returns)
        msg["ep_length"] = encode_array(wire.episode_lengths)
        msg["ep_success"] = encode_array(wire.episode_successes)
    payload = _pack(msg)
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
    )


def decode_transitions(payload: Any, *, obs_dim: int | None = None, act_dim: int | None = None,
                       priv_dim: int | None = None, limits: Limits = DEFAULT_LIMITS) -> TransitionBatch:
    """Checked TransitionBatch; ``obs_dim``/``act_dim`` are what the receiver's env expects and
    ``priv_dim`` the privileged-state width its critic expects (0: none may come; None: any)."""
    r = _Reader(_unpack(payload, limits), T_TRANSITIONS, limits)
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
    )
    r.finish()
    _check_batch_shapes(batch, obs_dim, act_dim, limits)
    _check_extras(batch, priv_dim)
    return batch


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
    payload = _pack(msg)
    decode_weights(payload, limits=limits)
    return payload


def decode_weights(payload: Any, *, expected: Mapping[str, tuple[int, ...]] | None = None,
                   limits: Limits = DEFAULT_LIMITS) -> Weights:
    """Checked Weights; ``expected`` (name -> shape) rejects a policy of another architecture."""
    r = _Reader(_unpack(payload, limits), T_WEIGHTS, limits)
    version, step, sent = r.integer("policy_version"), r.integer("step"), r.number("time", 0.0)
    raw = r.raw("params")
    if not isinstance(raw, dict) or not raw:
        raise ProtocolError(R_FIELD, "params must be a non-empty map of name -> array")
    params = {}
    for name, spec in raw.items():
        if not isinstance(name, str) or not 0 < len(name) <= 256:
            raise ProtocolError(R_FIELD, "param names must be strings of 1..256 chars")
        params[name] = decode_array(spec, f"params.{name}", WEIGHT_DTYPES, limits)
    meta = r.tree("meta", _json_leaf, "JSON data", {}, lists=True)
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
           "id": validate_name(s.id, "id"), "time": float(s.time), "values": _numbers_to_wire(s.values)}
    payload = _pack(msg)
    decode_stats(payload, limits=limits)
    return payload


def decode_stats(payload: Any, *, limits: Limits = DEFAULT_LIMITS) -> Stats:
    r = _Reader(_unpack(payload, limits), T_STATS, limits)
    stats = Stats(service=r.name("service"), id=r.name("id"), time=r.number("time", 0.0),
                  values=r.tree("values", _number_leaf, "a number or null"))
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
           "metrics": _numbers_to_wire(c.metrics)}
    payload = _pack(msg)
    decode_checkpoint(payload, limits=limits)
    return payload


def decode_checkpoint(payload: Any, *, limits: Limits = DEFAULT_LIMITS) -> Checkpoint:
    r = _Reader(_unpack(payload, limits), T_CHECKPOINT, limits)
    ckpt = Checkpoint(step=r.integer("step"), path=r.text("path"), policy_version=r.integer("policy_version", 0),
                      time=r.number("time", 0.0), metrics=r.tree("metrics", _number_leaf, "a number or null", {}))
    if not ckpt.path:
        raise ProtocolError(R_FIELD, "path is empty")
    r.finish()
    return ckpt


def message_type(payload: Any, limits: Limits = DEFAULT_LIMITS) -> str:
    """The ``t`` of a payload of this protocol version (for tools that sniff a key)."""
    obj = _unpack(payload, limits)
    if not _is_int(obj.get("v")) or obj.get("v") != PROTOCOL_VERSION:
        raise ProtocolError(R_VERSION, f"v={obj.get('v')!r}")
    if obj.get("t") not in (T_TRANSITIONS, T_WEIGHTS, T_STATS, T_CHECKPOINT):
        raise ProtocolError(R_TYPE, f"t={obj.get('t')!r}")
    return obj["t"]


# --------------------------------------------------------------------------------------------
# Counting rejects
# --------------------------------------------------------------------------------------------

class RejectCounter:
    """Thread-safe tally of accepted and rejected messages, by ProtocolError reason.

    Services call :meth:`reject` in their ``except ProtocolError`` branch and publish
    :meth:`counts` in their stats; the return value lets them log only the first few.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()
        self._accepted = 0
        self.last_error: str | None = None

    def reject(self, error: ProtocolError | str) -> int:
        """Count one rejected message; returns how many of this reason so far."""
        reason = error.reason if isinstance(error, ProtocolError) else str(error)
        with self._lock:
            self._counts[reason] += 1
            self.last_error = str(error)
            return self._counts[reason]

    def accept(self, n: int = 1) -> None:
        with self._lock:
            self._accepted += n

    @property
    def accepted(self) -> int:
        with self._lock:
            return self._accepted

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self._counts.values())

    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)
