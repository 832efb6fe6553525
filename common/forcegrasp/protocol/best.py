"""The ``best`` message: the evaluator's current best policy, its scores and the file's bytes.

The evaluator answers queries on ``forcegrasp/<run>/best`` with it (``forcegrasp_evaluator``'s
endpoint); ``forcegrasp best`` and third-party clients decode it here, with every check a
receiver needs: fields, types, the SHA-256 of the policy bytes, and the policy file itself.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import asdict, dataclass

from forcegrasp.policy_file import PolicyFileError, load_policy_bytes
from forcegrasp.protocol.wire import DEFAULT_LIMITS, PROTOCOL_VERSION, R_FIELD, T_BEST, Limits, ProtocolError, Reader, checked, unpack

_SHA_LEN = 64



@dataclass
class BestPolicy:
    """The evaluator's current best checkpoint: scores, provenance and the policy file bytes.

    ``score``/``success_rate``/``episodes`` are the final ranking (mean return over the rank
    placements, the paper's 100 random tests); ``eval_*`` the periodic evaluation that got it
    into the top k.
    """

    run: str
    step: int
    score: float
    success_rate: float
    episodes: int
    eval_score: float
    eval_success_rate: float
    eval_episodes: int
    object: str
    force_feedback: bool
    policy_version: int
    sha256: str
    policy: bytes
    time: float = 0.0

    def metadata(self) -> dict:
        """Everything but the policy bytes, JSON-ready."""
        out = asdict(self)
        out.pop("policy")
        out["size"] = len(self.policy)
        return out


def encode_best(b: BestPolicy, limits: Limits = DEFAULT_LIMITS) -> bytes:
    msg = {"v": PROTOCOL_VERSION, "t": T_BEST, **{k: v for k, v in asdict(b).items()}}
    msg["time"] = float(msg["time"] or time.time())
    return checked(msg, decode_best, limits)


def decode_best(payload, *, limits: Limits = DEFAULT_LIMITS) -> BestPolicy:
    """A checked ``best`` message: fields, types, SHA-256 of the policy, and the policy file
    itself (parsed, and its object / force-feedback flag equal to the message's)."""
    r = Reader(unpack(payload, limits), T_BEST, limits)
    ff = r.raw("force_feedback")
    if not isinstance(ff, bool):
        raise ProtocolError(R_FIELD, "force_feedback must be a boolean")
    policy = r.raw("policy")
    if not isinstance(policy, bytes) or not policy:
        raise ProtocolError(R_FIELD, "policy must be non-empty msgpack bin (the policy file's bytes)")
    sha = r.text("sha256", max_len=_SHA_LEN)
    best = BestPolicy(
        run=r.name("run"), step=r.integer("step"), score=r.number("score"), success_rate=r.number("success_rate"),
        episodes=r.integer("episodes"), eval_score=r.number("eval_score"),
        eval_success_rate=r.number("eval_success_rate"), eval_episodes=r.integer("eval_episodes"),
        object=r.text("object", max_len=256), force_feedback=ff, policy_version=r.integer("policy_version"),
        sha256=sha, policy=policy, time=r.number("time", 0.0))
    r.finish()
    if hashlib.sha256(policy).hexdigest() != sha:
        raise ProtocolError(R_FIELD, "sha256 does not match the policy bytes")
    try:
        _, meta = load_policy_bytes(policy, source="best.policy")
    except PolicyFileError as exc:
        raise ProtocolError(R_FIELD, f"policy is not a valid policy file: {exc}") from None
    if meta.object_name != best.object or meta.force_feedback != best.force_feedback:
        raise ProtocolError(R_FIELD, f"policy file is for {meta.object_name!r} (force feedback "
                                     f"{meta.force_feedback}), the message says {best.object!r} ({best.force_feedback})")
    return best
