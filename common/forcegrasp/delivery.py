"""Delivery of transitions from actors to the learner: the sender's and the receiver's rules in one
place, so the guarantee can be read (and tested) as a whole.

- Every actor process numbers its batches: ``epoch`` is random per process start, ``seq`` counts
  from 0. The learner's :class:`Streams` reads them per actor: a new epoch is a restarted process,
  a ``seq`` it already has a resend (dropped, counted as a duplicate). A batch that arrives past a
  hole is admitted and held *ahead*; the acknowledgement is the last seq with nothing missing
  before it, so a hole is never acknowledged. Holes still open when too much is held ahead
  (``MAX_AHEAD``) or when the actor restarts are counted as gaps: batches lost for good.
- The actor's :class:`Outbox` keeps every batch until the learner acknowledges it (the
  ``acked`` map of its progress message). While no learner listens, batches wait in a bounded
  outbox (oldest dropped first, counted); when a learner appears again, everything sent but not
  acknowledged goes again, first. A batch still unacknowledged ``RESEND_AFTER_S`` after it was
  sent goes again too (with everything after it): a link can lose what was in flight without the
  actor ever seeing the learner gone. The learner's duplicate check makes resends harmless.
- Flow control: the progress message also carries the learner's *headroom* (how many more
  transitions it takes before it owes too many updates). The actor pauses while the headroom,
  less what it sent since that word, is used up; a learner that is gone releases it.
"""

from __future__ import annotations

import collections
import dataclasses
import time
from typing import Callable

from forcegrasp.protocol import Progress, TransitionBatch

RESEND_AFTER_S = 5.0  # an unacknowledged batch this old is sent again (progress acks come at ~20 Hz)
MAX_AHEAD = 4096  # batches held past a hole before the hole counts as lost


# --------------------------------------------------------------------------------------------
# Sender side (actors)
# --------------------------------------------------------------------------------------------

class Outbox:
    """One actor's batches on their way to the learner (encoded payloads, with their seq)."""

    def __init__(self, actor_id: str, epoch: int, max_batches: int):
        self.actor_id, self.epoch, self.max_batches = actor_id, epoch, max_batches
        self.waiting: collections.deque[tuple[int, bytes, int]] = collections.deque()  # (seq, payload, n)
        self.unacked: collections.deque[tuple[int, bytes, int]] = collections.deque()  # sent, not yet ingested
        self._oldest_sent_at = 0.0  # when the batch now first in `unacked` was (re)sent
        self.sent_batches = 0
        self.resent_batches = 0
        self.dropped_batches = 0
        self.acked_transitions = 0  # what the learner confirmed it ingested: the loss-free count
        self._headroom: float | None = None
        self._sent_since_progress = 0
        self._was_present = False

    def put(self, seq: int, payload: bytes, n: int) -> None:
        """Queue a batch of ``n`` transitions; past the bound the oldest unsent-or-unacked goes."""
        self.waiting.append((seq, payload, n))
        while len(self.waiting) + len(self.unacked) > self.max_batches:
            (self.unacked or self.waiting).popleft()
            self.dropped_batches += 1

    def on_progress(self, progress: Progress) -> None:
        """The learner's latest word: its headroom, and which of our batches it has ingested."""
        self._headroom = progress.headroom
        self._sent_since_progress = 0
        acked = progress.acked.get(self.actor_id)
        if acked is not None and acked[0] == self.epoch:
            popped = False
            while self.unacked and self.unacked[0][0] <= acked[1]:
                self.acked_transitions += self.unacked.popleft()[2]
                popped = True
            if popped:  # the batch now oldest was sent no earlier than this ack's news
                self._oldest_sent_at = time.monotonic()

    def must_wait(self, learner_present: bool) -> bool:
        """True while a live learner says the actors are ahead of its update-to-data ratio.

        A learner busy in a long step sends no news but is still there (its subscriber still
        matches): its last word holds. A learner that is gone releases the actor, which then
        fills its bounded outbox.
        """
        if self._headroom is None or not learner_present:
            return False
        return self._headroom - self._sent_since_progress <= 0

    def flush(self, learner_present: bool, put: Callable[[bytes], None], now: float | None = None) -> None:
        """Send what waits, if a learner listens; after an outage, or when the oldest unacknowledged
        batch is `RESEND_AFTER_S` old, the unacknowledged go (again) first."""
        now = time.monotonic() if now is None else now
        stale = self.unacked and now - self._oldest_sent_at > RESEND_AFTER_S
        if learner_present and self.unacked and (not self._was_present or stale):
            self.resent_batches += len(self.unacked)
            self.waiting.extendleft(reversed(self.unacked))
            self.unacked.clear()
        self._was_present = learner_present
        while learner_present and self.waiting:
            item = self.waiting.popleft()
            put(item[1])
            if not self.unacked:
                self._oldest_sent_at = now
            self.unacked.append(item)
            self.sent_batches += 1
            self._sent_since_progress += item[2]

    def stats(self) -> dict:
        return {"sent_batches": self.sent_batches, "buffered_batches": len(self.waiting),
                "unacked_batches": len(self.unacked), "resent_batches": self.resent_batches,
                "dropped_batches": self.dropped_batches, "acked_transitions": self.acked_transitions}


# --------------------------------------------------------------------------------------------
# Receiver side (the learner)
# --------------------------------------------------------------------------------------------

@dataclasses.dataclass
class Stream:
    """What the learner knows about one actor's stream."""

    last_seq: int = -1  # every seq up to here is in (the acknowledgement)
    epoch: int | None = None
    ahead: set = dataclasses.field(default_factory=set)  # admitted seqs past a hole
    restarts: int = 0
    duplicates: int = 0
    ingested: int = 0
    gaps: int = 0
    staleness_sum: float = 0.0
    batches: int = 0
    rate_mark: tuple[float, int] = (0.0, 0)
    last_seen: float = dataclasses.field(default_factory=time.monotonic)  # last batch, new or resent


#: Actors silent this long drop out of the progress acknowledgements and the stats: replaced
#: actors (a new id each, as compose replicas get) would otherwise grow both messages forever.
#: Their stream state stays, so a late resend is still told apart from new data.
ACTIVE_S = 60.0


class Streams:
    """Every actor's stream as the learner sees it: restarts, resends and losses told apart."""

    def __init__(self) -> None:
        self.by_actor: dict[str, Stream] = collections.defaultdict(Stream)

    def active(self, within: float = ACTIVE_S) -> dict[str, Stream]:
        """The streams that sent a batch in the last ``within`` seconds."""
        now = time.monotonic()
        return {a: s for a, s in self.by_actor.items() if s.epoch is not None and now - s.last_seen <= within}

    def admit(self, batch: TransitionBatch, policy_version: int) -> bool:
        """Whether ``batch`` is new data (False: a resend already in replay). Counts gaps,
        restarts, and how many policy versions behind the learner the actor acted."""
        s = self.by_actor[batch.actor_id]
        s.last_seen = time.monotonic()
        if batch.epoch != s.epoch:  # first contact, or a restarted actor counting from 0 again
            if s.epoch is not None:
                s.restarts += 1
                s.gaps += _holes(s)  # what the old process never delivered is lost for good
            s.epoch, s.last_seq, s.ahead = batch.epoch, batch.seq - 1, set()
        if batch.seq <= s.last_seq or batch.seq in s.ahead:
            s.duplicates += 1
            return False
        s.ahead.add(batch.seq)
        while s.last_seq + 1 in s.ahead:
            s.ahead.remove(s.last_seq + 1)
            s.last_seq += 1
        if len(s.ahead) > MAX_AHEAD:  # waited long enough: the holes count as lost, acks move on
            s.gaps += _holes(s)
            s.last_seq, s.ahead = max(s.ahead), set()
        s.batches += 1
        s.ingested += batch.n
        s.staleness_sum += policy_version - batch.policy_version
        return True

    def snapshot(self) -> dict[str, list[int]]:
        """``{actor: [epoch, last_seq, ingested, ahead, gaps]}``, for the learner's checkpoint."""
        return {a: [s.epoch, s.last_seq, s.ingested, sorted(s.ahead), s.gaps] for a, s in self.by_actor.items()
                if s.epoch is not None}

    @classmethod
    def restore(cls, saved) -> "Streams":
        """Streams as `snapshot` left them; malformed entries (a hand-edited file) are skipped."""
        out = cls()
        for actor_id, value in (saved.items() if isinstance(saved, dict) else ()):
            if (isinstance(value, list) and len(value) == 5 and all(isinstance(v, int) for v in value[:3])
                    and isinstance(value[4], int) and isinstance(value[3], list)
                    and all(isinstance(v, int) for v in value[3][:MAX_AHEAD])):
                out.by_actor[str(actor_id)] = Stream(last_seq=value[1], epoch=value[0], ingested=value[2],
                                                     ahead=set(value[3][:MAX_AHEAD]), gaps=value[4])
        return out

    def acked(self) -> dict[str, tuple[int, int]]:
        """Per active actor, the (epoch, seq) of the last batch admitted: the progress message's acks."""
        return {a: (s.epoch, s.last_seq) for a, s in self.active().items()}

    @property
    def gaps(self) -> int:
        """Batches lost for good, plus the holes still open now."""
        return sum(s.gaps + _holes(s) for s in self.by_actor.values())

    def stats(self) -> dict[str, dict]:
        """Per active actor, its counters and its ingest rate since the previous call."""
        now = time.monotonic()
        out = {}
        for actor_id, s in self.active().items():
            t_prev, n_prev = s.rate_mark
            rate = (s.ingested - n_prev) / (now - t_prev) if t_prev else 0.0
            s.rate_mark = (now, s.ingested)
            out[actor_id] = {"ingested": s.ingested, "per_s": rate, "last_seq": s.last_seq, "gaps": s.gaps + _holes(s),
                             "restarts": s.restarts, "duplicates": s.duplicates,
                             "staleness": s.staleness_sum / s.batches if s.batches else 0.0}
        return out


def _holes(s: Stream) -> int:
    """Batches missing below the highest one held ahead."""
    return (max(s.ahead) - s.last_seq - len(s.ahead)) if s.ahead else 0
