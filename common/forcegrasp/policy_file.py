"""Policy files: one safetensors file holding the actor weights and, in its header, JSON metadata.

Layout (a standard safetensors file, readable by any safetensors tool):

* tensors: ``layers.{i}.weight`` ``(out, in)`` and ``layers.{i}.bias`` ``(out,)``, float32, for the
  actor MLP ``obs_dim -> hidden... -> 2 * act_dim`` (mean then log-std);
* header ``__metadata__``: a single key ``"forcegrasp.policy"`` whose value is the JSON of
  `PolicyMetadata` (format version, observation/action layouts, object, force-feedback flag,
  training steps, evaluation score, hidden sizes, action scaling, log-std bounds). Version 2: the
  action scaling (``action_low``/``action_high``, the env units of actions -1 and +1) is required.

One file (rather than a JSON sidecar) so a download or a network message can never pair weights
with the wrong metadata. Reading never unpickles: safetensors is a JSON header plus raw little-endian
buffers. Every way a file can be wrong (truncated, corrupt, other version, shapes not matching the
metadata) raises `PolicyFileError` naming the problem. Writes are atomic (`atomic_write`).
"""

from __future__ import annotations

import json
import os
import struct
import tempfile
from contextlib import contextmanager, suppress
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from safetensors import SafetensorError
from safetensors.numpy import load as _st_load, save as _st_save

FORMAT_NAME = "forcegrasp-policy"
FORMAT_VERSION = 2
METADATA_KEY = "forcegrasp.policy"
_MAX_HEADER = 16 * 1024 * 1024  # a policy header is a few kB; anything huge is corruption


class PolicyFileError(ValueError):
    """A policy file (or policy bytes) that cannot be used, with the reason in the message."""


@contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb"):
    """Open a temporary file next to `path`; on success fsync it and rename it over `path`.

    A crash or exception before the rename leaves the previous file untouched (the temporary is
    removed), so readers only ever see the old complete file or the new complete file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    with suppress(OSError):  # make the rename itself durable; not possible on every filesystem
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


@dataclass
class PolicyMetadata:
    """What a policy file says about the policy besides its weights."""

    obs_layout: list[tuple[str, int]]  # named observation segments, in order; sizes sum to obs_dim
    action_layout: list[tuple[str, int]]  # named action segments; sizes sum to act_dim
    hidden: tuple[int, ...] = (256, 256)
    object_name: str = ""
    force_feedback: bool = True
    training_steps: int = 0
    eval_score: float | None = None
    action_low: list[float] | None = None  # env units that action -1 maps to (required in a file)
    action_high: list[float] | None = None  # env units that action +1 maps to (required in a file)
    log_std_bounds: tuple[float, float] = (-20.0, 2.0)
    obs_norm: bool = False  # the file carries obs_mean/obs_std; the actor sees (obs - mean) / std, clipped
    extra: dict = field(default_factory=dict)  # free-form JSON (e.g. run id, seed)
    format_version: int = FORMAT_VERSION

    def __post_init__(self):
        self.obs_layout = [(str(n), int(s)) for n, s in self.obs_layout]
        self.action_layout = [(str(n), int(s)) for n, s in self.action_layout]
        self.hidden = tuple(int(h) for h in self.hidden)
        self.log_std_bounds = tuple(float(b) for b in self.log_std_bounds)

    @property
    def obs_dim(self) -> int:
        return sum(size for _, size in self.obs_layout)

    @property
    def act_dim(self) -> int:
        return sum(size for _, size in self.action_layout)

    def to_json(self) -> str:
        return json.dumps({"format": FORMAT_NAME, **asdict(self)}, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "PolicyMetadata":
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as exc:
            raise PolicyFileError(f"policy metadata is not valid JSON: {exc}") from None
        if not isinstance(raw, dict) or raw.get("format") != FORMAT_NAME:
            raise PolicyFileError(f"not a ForceGrasp policy (metadata 'format' is not {FORMAT_NAME!r})")
        version = raw.get("format_version")
        if version != FORMAT_VERSION:
            supported = f"policy file format version {version!r} is not supported (this ForceGrasp reads version {FORMAT_VERSION})"
            if isinstance(version, int) and version > FORMAT_VERSION:
                raise PolicyFileError(f"{supported}: it was written by a newer ForceGrasp")
            raise PolicyFileError(
                f"{supported}: to use it, re-save its weights as version {FORMAT_VERSION}, whose metadata must "
                "record action_low/action_high (the env units of actions -1 and +1: the action step sizes "
                "it was trained with), or train the policy again"
            )
        raw.pop("format")
        known = set(cls.__dataclass_fields__)
        unknown = set(raw) - known
        if unknown:
            raise PolicyFileError(f"policy metadata has unknown fields {sorted(unknown)}")
        try:
            meta = cls(**raw)
        except (TypeError, ValueError) as exc:
            raise PolicyFileError(f"policy metadata is malformed: {exc}") from None
        meta.validate()
        return meta

    def validate(self) -> None:
        """Raise `PolicyFileError` if the metadata cannot describe a usable actor."""
        problems = []
        if any(s <= 0 for _, s in self.obs_layout) or not self.obs_layout:
            problems.append(f"observation layout {self.obs_layout} needs positive sizes")
        if any(s <= 0 for _, s in self.action_layout) or not self.action_layout:
            problems.append(f"action layout {self.action_layout} needs positive sizes")
        if not self.hidden or any(h <= 0 for h in self.hidden):
            problems.append(f"hidden sizes {self.hidden} must be positive")
        for name in ("action_low", "action_high"):
            value = getattr(self, name)
            if value is None:
                problems.append(f"{name} is missing (format version {FORMAT_VERSION} records the action scaling)")
            elif len(value) != self.act_dim:
                problems.append(f"{name} has {len(value)} entries for {self.act_dim} action dimensions")
        if len(self.log_std_bounds) != 2:
            problems.append(f"log_std_bounds {self.log_std_bounds} must be (min, max)")
        if problems:
            raise PolicyFileError("policy metadata is inconsistent: " + "; ".join(problems))


def actor_param_shapes(meta: PolicyMetadata) -> dict[str, tuple[int, ...]]:
    """The exact tensor names and shapes an actor described by `meta` has."""
    dims = [meta.obs_dim, *meta.hidden, 2 * meta.act_dim]
    shapes = {}
    for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
        shapes[f"layers.{i}.weight"] = (d_out, d_in)
        shapes[f"layers.{i}.bias"] = (d_out,)
    if meta.obs_norm:
        shapes["obs_mean"] = shapes["obs_std"] = (meta.obs_dim,)
    return shapes


def policy_to_bytes(weights: dict[str, np.ndarray], meta: PolicyMetadata) -> bytes:
    """Serialise after checking that the weights are exactly what the metadata describes."""
    meta.validate()
    arrays = {k: np.ascontiguousarray(np.asarray(v, dtype=np.float32)) for k, v in weights.items()}
    _check_weights(arrays, meta)
    return _st_save(arrays, metadata={METADATA_KEY: meta.to_json()})


def save_policy_file(path: str | os.PathLike, weights: dict[str, np.ndarray], meta: PolicyMetadata) -> Path:
    """Write a policy file atomically; returns the path."""
    data = policy_to_bytes(weights, meta)
    with atomic_write(path) as f:
        f.write(data)
    return Path(path)


def load_policy_bytes(data: bytes, source: str = "policy data") -> tuple[dict[str, np.ndarray], PolicyMetadata]:
    """Parse and fully validate policy bytes; returns ``(weights, metadata)``."""
    data = bytes(data)
    if len(data) < 8:
        raise PolicyFileError(f"{source}: truncated ({len(data)} bytes; a policy file has at least an 8-byte header length)")
    (header_len,) = struct.unpack("<Q", data[:8])
    if header_len > _MAX_HEADER or 8 + header_len > len(data):
        raise PolicyFileError(
            f"{source}: truncated or corrupt (header claims {header_len} bytes, file has {len(data) - 8} after the length)"
        )
    try:
        header = json.loads(data[8 : 8 + header_len])
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise PolicyFileError(f"{source}: corrupt (the safetensors header is not valid JSON)") from None
    if not isinstance(header, dict):
        raise PolicyFileError(f"{source}: corrupt (the safetensors header is not a JSON object)")
    text = (header.get("__metadata__") or {}).get(METADATA_KEY)
    if text is None:
        raise PolicyFileError(f"{source}: a safetensors file without ForceGrasp policy metadata ({METADATA_KEY!r})")
    meta = PolicyMetadata.from_json(text)
    try:
        end = max((int(max(t["data_offsets"])) for k, t in header.items() if k != "__metadata__"), default=0)
    except (KeyError, TypeError, ValueError):
        raise PolicyFileError(f"{source}: corrupt (a tensor entry in the header has no valid data_offsets)") from None
    if 8 + header_len + end != len(data):
        raise PolicyFileError(
            f"{source}: truncated or corrupt (tensor data should be {end} bytes, found {len(data) - 8 - header_len})"
        )
    try:
        weights = _st_load(data)
    except SafetensorError as exc:
        raise PolicyFileError(f"{source}: corrupt tensor data ({exc})") from None
    _check_weights(weights, meta, source)
    return weights, meta


def load_policy_file(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], PolicyMetadata]:
    """Read a policy file; raises `PolicyFileError` (or `FileNotFoundError`) with the reason."""
    return load_policy_bytes(Path(path).read_bytes(), source=str(path))


def _check_weights(weights: dict[str, np.ndarray], meta: PolicyMetadata, source: str = "policy") -> None:
    expected = actor_param_shapes(meta)
    missing, unexpected = sorted(set(expected) - set(weights)), sorted(set(weights) - set(expected))
    if missing or unexpected:
        raise PolicyFileError(f"{source}: tensors do not match the metadata (missing {missing}, unexpected {unexpected})")
    for name, shape in expected.items():
        w = weights[name]
        if w.dtype != np.float32:
            raise PolicyFileError(f"{source}: tensor {name!r} is {w.dtype}, expected float32")
        if tuple(w.shape) != shape:
            raise PolicyFileError(
                f"{source}: tensor {name!r} has shape {tuple(w.shape)} but the metadata "
                f"(obs {meta.obs_dim}, hidden {list(meta.hidden)}, action {meta.act_dim}) needs {shape}"
            )
        if not np.all(np.isfinite(w)):
            raise PolicyFileError(f"{source}: tensor {name!r} contains NaN or inf")
    if meta.obs_norm and not np.all(weights["obs_std"] > 0):
        raise PolicyFileError(f"{source}: obs_std must be positive everywhere")
