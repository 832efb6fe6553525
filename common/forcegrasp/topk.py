"""The evaluator's top-k folder: the k best checkpoints on disk, with a JSON index, crash-safe.

Layout of ``<output_dir>/<run>/evaluator/top/``::

    index.json                       what is in the top k, their scores, the best, the history
    policy-000012000.safetensors     one policy file per member (its metadata carries the scores)

Rules that keep the folder consistent under ``kill -9`` at any moment:

1. every file is written to a temporary name, fsynced and renamed (``atomic_write``);
2. a new member's policy file is written *before* the index that names it;
3. the index is written last; files it no longer names are deleted only *after* it.

So the index on disk always names complete, verified files. What a crash can leave behind is
only extra: a temporary file or a policy file the index does not name. :meth:`TopK.load` removes
those, re-verifies every member (size, SHA-256, a full policy-file parse) and drops, with a log
line, any member whose file is missing or corrupt (a disk problem or a person's hand, never a
crash of this code), then rewrites the index.

Membership is by the periodic evaluation score (mean return on the fixed ``eval`` placements),
ties to the earlier checkpoint. Among the members the best is the one with the highest final
ranking score (mean return on the ``rank`` placements, the paper's 100 random tests). Ranking
placements are fixed too, so a member's ranking score is computed once, when it enters, and
stays valid: re-ranking after a change only has to score the newcomer.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable

from forcegrasp.policy_file import PolicyFileError, atomic_write, load_policy_bytes

from forcegrasp.rundir import INDEX_NAME, policy_file_name, step_of  # noqa: F401  (policy_file_name: re-exported)

log = logging.getLogger("forcegrasp.evaluator")

INDEX_FORMAT = "forcegrasp-evaluator-top"
INDEX_VERSION = 1
MAX_POLICY_BYTES = 256 * 1024 * 1024
HISTORY_LIMIT = 100_000


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@dataclass
class Member:
    """One checkpoint in the top k."""

    file: str
    step: int
    score: float              # mean return on the eval placements (membership)
    success_rate: float
    episodes: int
    rank_score: float         # mean return on the rank placements (choice of the best)
    rank_success_rate: float
    rank_episodes: int
    sha256: str
    size: int
    object: str
    force_feedback: bool
    policy_version: int = 0
    evaluated_at: float = 0.0
    conditions: dict = field(default_factory=dict)  # the rank score per test condition, when several are mixed
    objects: dict = field(default_factory=dict)  # the rank figures per object, when a run trains several

    def membership_key(self) -> tuple:
        return (-self.score, self.step)

    def best_key(self) -> tuple:
        return (-self.rank_score, -self.score, self.step)

    @classmethod
    def from_json(cls, raw: Any) -> "Member":
        if not isinstance(raw, dict):
            raise ValueError("member is not a JSON object")
        names = {f.name for f in fields(cls)}
        missing = sorted(names - set(raw) - {"policy_version", "evaluated_at", "conditions", "objects"})
        if missing:
            raise ValueError(f"member misses {missing}")
        member = cls(**{k: raw[k] for k in names if k in raw})
        if step_of(member.file) != member.step:
            raise ValueError(f"file name {member.file!r} does not match step {member.step}")
        for name in ("score", "success_rate", "rank_score", "rank_success_rate"):
            if not isinstance(getattr(member, name), (int, float)) or isinstance(getattr(member, name), bool):
                raise ValueError(f"{name} is not a number")
        if not isinstance(member.sha256, str) or not re.fullmatch(r"[0-9a-f]{64}", member.sha256):
            raise ValueError("sha256 is not 64 hex digits")
        return member


def would_enter(members: list[Member], k: int, score: float, step: int) -> bool:
    """Whether a checkpoint scoring ``score`` at ``step`` belongs in a top ``k`` of ``members``."""
    if any(m.step == step for m in members):
        return False
    if len(members) < k:
        return True
    worst = max(members, key=Member.membership_key)
    return (-score, step) < worst.membership_key()


class TopK:
    """The top-k folder of one run (see the module docstring for the crash-safety rules)."""

    def __init__(self, folder: str | os.PathLike, k: int, run: str = ""):
        if k < 1:
            raise ValueError("k must be >= 1")
        self.folder = Path(folder)
        self.k = int(k)
        self.run = run
        self.members: list[Member] = []
        self.history: list[dict] = []
        self.last_step: int | None = None
        self.protocol: dict = {}
        self._evicted: list[str] = []
        self.crash_hook: Callable[[str], None] | None = None  # fault injection for the crash tests

    # ------------------------------------------------------------------ reading
    @property
    def index_path(self) -> Path:
        return self.folder / INDEX_NAME

    @property
    def best(self) -> Member | None:
        return min(self.members, key=Member.best_key) if self.members else None

    def path_of(self, member: Member) -> Path:
        return self.folder / member.file

    def read_policy(self, member: Member) -> bytes:
        """The member's policy bytes, checked against the index (PolicyFileError otherwise)."""
        path = self.path_of(member)
        try:
            size = path.stat().st_size
            if size != member.size or size > MAX_POLICY_BYTES:
                raise PolicyFileError(f"{path}: {size} bytes, the index says {member.size}")
            data = path.read_bytes()
        except OSError as exc:
            raise PolicyFileError(f"{path}: cannot read ({exc.strerror or exc})") from None
        if sha256(data) != member.sha256:
            raise PolicyFileError(f"{path}: SHA-256 differs from the index (corrupt or replaced)")
        return data

    def load(self, protocol: dict | None = None) -> bool:
        """Read the index, verify every member, clean leftovers; True if the evaluation protocol
        recorded in the index differs from ``protocol`` (the members' scores need redoing)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        for leftover in self.folder.glob(".*.tmp"):
            log.info("removing %s (a write interrupted by a crash)", leftover)
            leftover.unlink(missing_ok=True)
        changed = False
        raw = self._read_index()
        self.members, self.history, self.last_step, self.protocol = [], [], None, {}
        if raw is not None:
            self.history = [h for h in raw.get("history", []) if isinstance(h, dict)][-HISTORY_LIMIT:]
            last = raw.get("last_step")
            self.last_step = last if isinstance(last, int) and not isinstance(last, bool) else None
            self.protocol = raw.get("protocol") if isinstance(raw.get("protocol"), dict) else {}
            for item in raw.get("members", []):
                try:
                    member = Member.from_json(item)
                    self._verify(member)
                except (ValueError, TypeError, PolicyFileError) as exc:
                    name = item.get("file") if isinstance(item, dict) else item
                    log.warning("top-k: dropping member %s: %s", name, exc)
                    changed = True
                    continue
                if any(m.step == member.step for m in self.members):
                    log.warning("top-k: dropping duplicate member %s", member.file)
                    changed = True
                    continue
                self.members.append(member)
        self.members = sorted(self.members, key=Member.membership_key)
        while len(self.members) > self.k:  # k lowered since the last run
            dropped = self.members.pop()
            log.info("top-k: k is %d now: %s leaves the top", self.k, dropped.file)
            changed = True
        named = {m.file for m in self.members}
        for path in self.folder.glob("policy-*.safetensors"):
            if path.name not in named:
                log.info("top-k: removing %s (not in the index: a save interrupted before its index, or evicted)",
                         path.name)
                path.unlink(missing_ok=True)
        protocol_changed = protocol is not None and raw is not None and self.protocol != protocol
        if protocol is not None:
            self.protocol = dict(protocol)
        if changed:
            self.commit()
        return protocol_changed and bool(self.members)

    def _read_index(self) -> dict | None:
        path = self.index_path
        if not path.exists():
            return None
        try:
            raw = json.loads(path.read_text())
            if not isinstance(raw, dict) or raw.get("format") != INDEX_FORMAT:
                raise ValueError(f"not a {INDEX_FORMAT} file")
            if raw.get("version") != INDEX_VERSION:
                raise ValueError(f"index version {raw.get('version')!r}, this evaluator reads {INDEX_VERSION}")
            return raw
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            aside = path.with_name(f"{INDEX_NAME}.bad-{int(time.time())}")
            log.error("top-k: %s is unreadable (%s); moved to %s, starting an empty top k", path, exc, aside.name)
            os.replace(path, aside)
            return None

    def _verify(self, member: Member) -> None:
        data = self.read_policy(member)
        load_policy_bytes(data, source=str(self.path_of(member)))

    # ------------------------------------------------------------------ changing
    def would_enter(self, score: float, step: int) -> bool:
        return would_enter(self.members, self.k, score, step)

    def record(self, step: int, score: float, success_rate: float, episodes: int, **extra) -> None:
        """Remember that ``step`` was evaluated (whether or not it enters); saved by :meth:`commit`."""
        self.history.append({"step": int(step), "score": float(score), "success_rate": float(success_rate),
                             "episodes": int(episodes), "time": time.time(), **extra})
        del self.history[:-HISTORY_LIMIT]
        self.last_step = step if self.last_step is None else max(self.last_step, step)

    def admit(self, member: Member, data: bytes) -> list[Member]:
        """Write the member's file (rule 2) and add it; returns the members pushed out of the top k.

        Nothing is final until :meth:`commit` writes the index.
        """
        if member.sha256 != sha256(data) or member.size != len(data):
            raise ValueError("member's sha256/size do not describe the data")
        with atomic_write(self.path_of(member)) as f:
            f.write(data)
        if self.crash_hook is not None:
            self.crash_hook("policy_written")
        # New lists, never in-place edits: the stats thread may be reading the old one.
        ranked = sorted([m for m in self.members if m.step != member.step] + [member], key=Member.membership_key)
        evicted = ranked[self.k:]
        self.members = ranked[: self.k]
        self._evicted.extend(m.file for m in evicted if m.file != member.file)
        if member in evicted:  # it did not make it after all: its file goes after the index
            self._evicted.append(member.file)
        return evicted

    def replace(self, member: Member, data: bytes) -> None:
        """Rewrite an existing member (re-scored under a new protocol) with its new file."""
        with atomic_write(self.path_of(member)) as f:
            f.write(data)
        self.members = sorted([m for m in self.members if m.step != member.step] + [member],
                              key=Member.membership_key)

    def to_json(self, with_history: bool = True) -> dict:
        best = self.best
        out = {
            "format": INDEX_FORMAT, "version": INDEX_VERSION, "run": self.run, "k": self.k,
            "updated": time.time(), "last_step": self.last_step, "evaluations": len(self.history),
            "best": best.file if best else None, "protocol": self.protocol,
            "members": [{**asdict(m), "best": m is best,
                         "rank": 1 + sorted(self.members, key=Member.best_key).index(m)} for m in self.members],
        }
        if with_history:
            out["history"] = self.history
        return out

    def commit(self) -> None:
        """Write the index (rule 3), then delete the files it no longer names."""
        text = json.dumps(self.to_json(), indent=1, allow_nan=False)
        with atomic_write(self.index_path, "w") as f:
            f.write(text)
        if self.crash_hook is not None:
            self.crash_hook("index_written")
        named = {m.file for m in self.members}
        for name in self._evicted:
            if name not in named:
                (self.folder / name).unlink(missing_ok=True)
        self._evicted.clear()


def check_folder(folder: str | os.PathLike, k: int | None = None) -> dict:
    """Validate a top-k folder from the outside (tests, operators): raises AssertionError with
    the problem, returns the index. Extra files (leftovers of a crash) are allowed; wrong ones
    named by the index are not."""
    folder = Path(folder)
    index = json.loads((folder / INDEX_NAME).read_text())
    assert index["format"] == INDEX_FORMAT and index["version"] == INDEX_VERSION, "not an index"
    members = [Member.from_json({k2: v for k2, v in m.items() if k2 not in ("best", "rank")})
               for m in index["members"]]
    assert k is None or len(members) <= k, f"{len(members)} members > k={k}"
    assert len({m.step for m in members}) == len(members), "duplicate members"
    assert [m.membership_key() for m in members] == sorted(m.membership_key() for m in members), "not sorted"
    for m in members:
        data = (folder / m.file).read_bytes()
        assert len(data) == m.size and sha256(data) == m.sha256, f"{m.file}: content differs from the index"
        load_policy_bytes(data, source=m.file)
    if members:
        best = min(members, key=Member.best_key)
        assert index["best"] == best.file, f"best is {index['best']}, should be {best.file}"
        assert [m["best"] for m in index["members"]].count(True) == 1
    else:
        assert index["best"] is None
    return index
