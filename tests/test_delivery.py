"""The delivery rules (forcegrasp.delivery) and the progress message that carries acknowledgements."""

from __future__ import annotations

import numpy as np
import pytest

from forcegrasp.delivery import Outbox, Streams
from forcegrasp.protocol import Progress, ProtocolError, TransitionBatch, decode_progress, encode_progress
from forcegrasp.protocol.wire import pack


def _batch(seq: int, epoch: int = 7, actor: str = "a", n: int = 4, version: int = 0) -> TransitionBatch:
    z = np.zeros((n, 3), np.float32)
    return TransitionBatch(actor_id=actor, seq=seq, epoch=epoch, policy_version=version, obs=z,
                           action=np.zeros((n, 2), np.float32), reward=np.zeros(n, np.float32), next_obs=z,
                           terminated=np.zeros(n, bool), truncated=np.zeros(n, bool))


def test_outbox_keeps_until_acked_and_resends_after_an_outage():
    box, wire = Outbox("a", epoch=7, max_batches=10), []
    for seq in range(3):
        box.put(seq, b"p%d" % seq, 4)
    box.flush(True, wire.append)
    assert wire == [b"p0", b"p1", b"p2"] and len(box.unacked) == 3
    box.on_progress(Progress(8, 0, None, {"a": (7, 1)}))  # the learner has 0 and 1
    assert [s for s, _, _ in box.unacked] == [2]
    box.on_progress(Progress(8, 0, None, {"a": (99, 5)}))  # an ack for another process of "a": ignored
    assert [s for s, _, _ in box.unacked] == [2]
    box.put(3, b"p3", 4)
    box.flush(False, wire.append)  # learner gone: nothing goes out
    assert len(wire) == 3
    box.flush(True, wire.append)  # back: the unacknowledged batch first, then the new one
    assert wire[3:] == [b"p2", b"p3"] and box.resent_batches == 1
    assert box.acked_transitions == 8  # batches 0 and 1, each counted once


def test_outbox_is_bounded_and_drops_the_oldest():
    box = Outbox("a", epoch=1, max_batches=3)
    for seq in range(5):
        box.put(seq, b"x", 1)
    assert [s for s, _, _ in box.waiting] == [2, 3, 4] and box.dropped_batches == 2


def test_outbox_pauses_on_used_up_headroom_only_while_a_learner_listens():
    box, wire = Outbox("a", epoch=1, max_batches=10), []
    assert not box.must_wait(True)  # no word from a learner yet
    box.on_progress(Progress(0, 0, headroom=6.0))
    box.put(0, b"x", 4)
    box.flush(True, wire.append)
    assert not box.must_wait(True)  # 6 - 4 > 0
    box.put(1, b"y", 4)
    box.flush(True, wire.append)
    assert box.must_wait(True) and not box.must_wait(False)
    box.on_progress(Progress(8, 0, headroom=None))  # a learner without a limit
    assert not box.must_wait(True)


def test_streams_tell_resends_gaps_and_restarts_apart():
    streams = Streams()
    assert streams.admit(_batch(0), 0) and streams.admit(_batch(1), 0)
    assert not streams.admit(_batch(1), 0)  # a resend
    assert streams.admit(_batch(4), 3)  # past a hole: admitted, held ahead, never acknowledged
    s = streams.by_actor["a"]
    assert (s.duplicates, s.ingested, s.last_seq, streams.gaps) == (1, 12, 1, 2)
    assert streams.acked() == {"a": (7, 1)}
    assert streams.admit(_batch(2), 3)  # the hole fills late (a resend after a lost send)
    assert streams.acked() == {"a": (7, 2)} and streams.gaps == 1
    assert not streams.admit(_batch(4), 3)  # already held ahead: a duplicate
    assert streams.admit(_batch(0, epoch=8), 3)  # a restarted process: its hole (3) is lost for good
    assert s.restarts == 1 and s.gaps == 1 and streams.acked() == {"a": (8, 0)}
    assert streams.stats()["a"]["staleness"] == pytest.approx(9 / 5)  # versions behind: 0, 0, 3, 3, 3


def test_replaced_actors_leave_the_acks_and_stats_but_their_resends_stay_duplicates(monkeypatch):
    """The soak replaced an actor every 5 s, each with a new id: the progress message (20 a second)
    and the stats would have grown by one entry per actor ever seen."""
    import forcegrasp.delivery as delivery

    clock = [1000.0]
    monkeypatch.setattr(delivery.time, "monotonic", lambda: clock[0])
    streams = Streams()
    assert streams.admit(_batch(0, actor="old"), 0)
    clock[0] += delivery.ACTIVE_S / 2
    assert streams.admit(_batch(0, actor="new"), 0)
    assert set(streams.acked()) == set(streams.stats()) == {"old", "new"}
    clock[0] += delivery.ACTIVE_S / 2 + 1  # "old" silent for longer than ACTIVE_S
    assert set(streams.acked()) == set(streams.stats()) == {"new"}
    assert "old" in streams.snapshot()  # kept for the checkpoint ...
    assert not streams.admit(_batch(0, actor="old"), 0)  # ... so a late resend is still a duplicate
    assert streams.acked()["old"] == (7, 0)  # and the actor is told its ack again


def test_a_batch_lost_in_flight_is_sent_again_and_the_hole_never_acknowledged(monkeypatch):
    """A link that drops what was in flight while the learner still looks present: the learner
    holds what came after the hole and acknowledges only up to it; the actor sends the
    unacknowledged again after RESEND_AFTER_S and the stream is whole."""
    from forcegrasp import delivery

    box, streams, wire = Outbox("a", epoch=7, max_batches=100), Streams(), []
    batches = {seq: _batch(seq) for seq in range(4)}
    for seq in range(4):
        box.put(seq, seq, 4)  # the payload stands for the batch
    box.flush(True, wire.append, now=0.0)
    for seq in wire:
        if seq != 1:  # batch 1 lost on the link
            streams.admit(batches[seq], 0)
    box.on_progress(Progress(12, 0, None, streams.acked()))
    assert [s for s, _, _ in box.unacked] == [1, 2, 3] and box.acked_transitions == 4
    wire.clear()
    box.flush(True, wire.append, now=1.0)
    assert wire == []  # too early to resend
    box._oldest_sent_at = 0.0
    box.flush(True, wire.append, now=delivery.RESEND_AFTER_S + 1.0)
    assert wire == [1, 2, 3] and box.resent_batches == 3
    for seq in wire:
        streams.admit(batches[seq], 0)
    box.on_progress(Progress(16, 0, None, streams.acked()))
    assert not box.unacked and box.acked_transitions == 16 == streams.by_actor["a"].ingested
    assert streams.gaps == 0 and streams.by_actor["a"].duplicates == 2


def test_streams_survive_a_learner_restart_through_its_checkpoint():
    """A batch ingested before the checkpoint but never acknowledged comes again from the actor:
    the restored learner drops it as a duplicate, acknowledges it, and counts the next one."""
    import json

    streams = Streams()
    assert streams.admit(_batch(0), 0) and streams.admit(_batch(1), 0)
    saved = json.loads(json.dumps(streams.snapshot()))  # as the checkpoint header stores it
    back = Streams.restore(saved)
    assert not back.admit(_batch(1), 0) and back.admit(_batch(2), 0)
    assert back.acked() == {"a": (7, 2)} and back.gaps == 0 and back.by_actor["a"].ingested == 12
    assert Streams.restore({"a": "junk", "b": [1], "c": [1, 2, 3, "x", 0]}).acked() == {}  # tampered: skipped


def test_progress_round_trip_and_hostile_fields():
    p = Progress(ingested=100, updates=25, headroom=-3.5, acked={"actor-0": (123, 4), "b": (0, 0)})
    back = decode_progress(encode_progress(p))
    assert (back.ingested, back.updates, back.headroom, back.acked) == (100, 25, -3.5, p.acked)
    assert decode_progress(encode_progress(Progress(0, 0, None))).headroom is None
    good = {"v": 1, "t": "progress", "ingested": 1, "updates": 1, "headroom": 1.0, "acked": {}, "time": 0.0}
    for bad in ({"acked": {"a": [1]}}, {"acked": {"a/b": [1, 2]}}, {"acked": {"a": [1.5, 2]}}, {"acked": []},
                {"headroom": float("nan")}, {"headroom": "x"}, {"ingested": -1}, {"extra": 1}):
        with pytest.raises(ProtocolError):
            decode_progress(pack({**good, **bad}))
    with pytest.raises(ProtocolError):
        decode_progress(pack({k: v for k, v in good.items() if k != "acked"}))
