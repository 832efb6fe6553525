"""The wire format every ForceGrasp message shares: msgpack maps with a version and a type tag,
raw little-endian arrays, bounded decoding, and the one error type receivers count.

Nothing here knows a message type; ``messages.py`` and ``best.py`` build on it.
"""

from __future__ import annotations

import math
import threading
from collections import Counter
from dataclasses import dataclass
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
T_PROGRESS = "progress"
T_BEST = "best"

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

INT64_MAX = 2**63 - 1
_FORBIDDEN_NAME_CHARS = frozenset("*$/#?")
_MAX_NAME_LEN = 128


class ProtocolError(ValueError):
    """A message (or a name) broke the protocol.  ``reason`` is one of :data:`REASONS`."""

    def __init__(self, reason: str, detail: str = "") -> None:
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}" if detail else reason)


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


def unpack(payload: Any, limits: Limits) -> dict:
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


def pack(obj: dict) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def checked(msg: dict, decode: Callable[..., Any], limits: Limits) -> bytes:
    """``msg`` packed, after the receiver's own ``decode`` accepted it: a sender never sends what
    its receivers would refuse."""
    payload = pack(msg)
    decode(payload, limits=limits)
    return payload


def is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def is_number(x: Any) -> bool:
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
            or not all(is_int(d) and d >= 0 for d in shape)):
        raise ProtocolError(R_SHAPE, f"{name}: shape must be a list of <= {limits.max_ndim} non-negative ints")
    if not isinstance(data, bytes):
        raise ProtocolError(R_FIELD, f"{name}: data must be msgpack bin, got {type(data).__name__}")
    np_dtype = _NP_DTYPES.get(dtype) or np.dtype(dtype)
    expected = math.prod(shape) * np_dtype.itemsize
    if expected != len(data):
        raise ProtocolError(R_SHAPE, f"{name}: {len(data)} data bytes, shape {shape} of {dtype} needs {expected}")
    arr = np.frombuffer(data, dtype=np_dtype).reshape(shape)
    check_values(arr, name)
    return arr


def check_values(arr: np.ndarray, name: str) -> None:
    """Floats must be finite; booleans must be 0/1 bytes (anything else is undefined in numpy)."""
    if arr.dtype.kind == "f" and arr.size and not np.isfinite(arr).all():
        raise ProtocolError(R_NONFINITE, f"{name}: contains NaN or infinity")
    if arr.dtype.kind == "b" and arr.size and arr.view(np.uint8).max() > 1:
        raise ProtocolError(R_FIELD, f"{name}: boolean bytes other than 0/1")


# --------------------------------------------------------------------------------------------
# Field reader shared by all message types
# --------------------------------------------------------------------------------------------

_REQUIRED = object()


class Reader:
    """Pulls typed fields out of a decoded map and remembers which ones were used."""

    def __init__(self, obj: dict, mtype: str, limits: Limits) -> None:
        version = obj.get("v")
        if not is_int(version) or version != PROTOCOL_VERSION:
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
        if not is_int(value) or not 0 <= value <= INT64_MAX:
            raise ProtocolError(R_FIELD, f"{name} must be an integer in [0, 2^63), got {value!r}")
        return value

    def number(self, name: str, default: Any = _REQUIRED) -> float:
        value = self._get(name, default)
        if not is_number(value) or not math.isfinite(value):
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
        check_tree(value, leaf, what, name, self.limits.max_depth, lists)
        return value

    def finish(self) -> None:
        extra = set(self.obj) - self.used
        if extra and not self.limits.allow_extra_fields:
            shown = sorted(map(repr, extra))[:5]
            raise ProtocolError(R_EXTRA, f"unknown fields {', '.join(shown)}")


def check_tree(value: Any, leaf: Callable[[Any], bool], what: str, path: str, depth: int,
                lists: bool) -> None:
    """Bounded-depth walk of a free-form structure: string-keyed maps, optional lists, leaves."""
    if depth < 0:
        raise ProtocolError(R_FIELD, f"{path}: nested deeper than the limit")
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise ProtocolError(R_FIELD, f"{path}: map keys must be strings")
            check_tree(item, leaf, what, f"{path}.{key}", depth - 1, lists)
    elif isinstance(value, list) and lists:
        for i, item in enumerate(value):
            check_tree(item, leaf, what, f"{path}[{i}]", depth - 1, lists)
    elif not leaf(value):
        reason = R_NONFINITE if isinstance(value, float) else R_FIELD
        raise ProtocolError(reason, f"{path}: {value!r}"[:120] + f" is not {what}")


def json_leaf(x: Any) -> bool:
    """JSON scalars with finite floats (the metadata of Weights)."""
    return x is None or isinstance(x, (bool, int, str)) or (isinstance(x, float) and math.isfinite(x))


def number_leaf(x: Any) -> bool:
    """Numbers for stats and metrics; ``None`` stands for "no value" (encoders map NaN to it)."""
    return x is None or isinstance(x, bool) or is_int(x) or (isinstance(x, float) and math.isfinite(x))


def numbers_to_wire(values: Mapping[str, Any], depth: int = DEFAULT_LIMITS.max_depth) -> dict:
    """Plain Python numbers for a stats tree: numpy scalars unwrapped, NaN/inf sent as ``None``."""
    if depth < 0:
        raise ProtocolError(R_FIELD, "stats nested too deep")
    out: dict = {}
    for key, value in values.items():
        if isinstance(value, Mapping):
            out[str(key)] = numbers_to_wire(value, depth - 1)
            continue
        if isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, float) and not math.isfinite(value):
            value = None
        if not number_leaf(value):
            raise ProtocolError(R_FIELD, f"stats value {key!r}={value!r} is not a number")
        out[str(key)] = value
    return out


def message_type(payload: Any, limits: Limits = DEFAULT_LIMITS) -> str:
    """The ``t`` of a payload of this protocol version (for tools that sniff a key)."""
    obj = unpack(payload, limits)
    if not is_int(obj.get("v")) or obj.get("v") != PROTOCOL_VERSION:
        raise ProtocolError(R_VERSION, f"v={obj.get('v')!r}")
    if obj.get("t") not in (T_TRANSITIONS, T_WEIGHTS, T_STATS, T_CHECKPOINT, T_PROGRESS, T_BEST):
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
