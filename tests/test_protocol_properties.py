"""Property-based hostile input: whatever arrives, a decoder returns a checked message or raises
ProtocolError (counted by reason by the services), never anything else (issue 12).

Three families of input, for every message type: arbitrary msgpack values; valid messages with
one field replaced by an arbitrary value; valid messages cut short or with bytes flipped.
"""

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from forcegrasp.protocol import (
    DEFAULT_LIMITS,
    Checkpoint,
    ProtocolError,
    Stats,
    TransitionBatch,
    Weights,
    Progress,
    decode_checkpoint,
    decode_progress,
    decode_stats,
    decode_transitions,
    decode_weights,
    encode_checkpoint,
    encode_progress,
    encode_stats,
    encode_transitions,
    encode_weights,
)

OBS, ACT, PRIV = 77, 7, 14
SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

scalars = st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(allow_nan=True),
                    st.text(max_size=20), st.binary(max_size=64))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=4)),
                      max_leaves=12)
arrays = st.fixed_dictionaries({"dtype": st.sampled_from(["<f4", "<f8", "|u1", "|b1", "<i4", "<i8", "O", "zz"]),
                                "shape": st.lists(st.integers(-3, 2**40), max_size=3),
                                "data": st.binary(max_size=256)})


def _batch(n=8):
    rng = np.random.default_rng(0)
    return TransitionBatch("a", 1, 2, rng.normal(size=(n, OBS)), rng.uniform(-1, 1, (n, ACT)), rng.normal(size=n),
                           rng.normal(size=(n, OBS)), np.zeros(n, bool), np.zeros(n, bool),
                           np.zeros(1, np.float32), np.ones(1, np.int32), np.ones(1, bool),
                           horizon=np.full(n, 3), privileged=rng.normal(size=(n, PRIV)),
                           next_privileged=rng.normal(size=(n, PRIV)))


VALID = {
    "transitions": (encode_transitions(_batch()),
                    lambda p: decode_transitions(p, obs_dim=OBS, act_dim=ACT, priv_dim=PRIV)),
    "weights": (encode_weights(Weights(3, 10, {"w": np.ones((4, 3), np.float32)}, meta={"k": 1})),
                lambda p: decode_weights(p, expected={"w": (4, 3)})),
    "stats": (encode_stats(Stats("learner", "0", {"a": 1.0, "b": {"c": 2}})), decode_stats),
    "checkpoint": (encode_checkpoint(Checkpoint(2000, "policy-000002000.safetensors", 3)), decode_checkpoint),
    "progress": (encode_progress(Progress(500, 120, 33.0, {"actor-0": (9, 4)})), decode_progress),
}


def _only_protocol_errors(decode, payload):
    try:
        decode(payload)
    except ProtocolError as exc:
        assert exc.reason  # every rejection names its reason (the services count by it)


@SETTINGS
@given(kind=st.sampled_from(sorted(VALID)), value=values)
def test_arbitrary_msgpack_values(kind, value):
    _only_protocol_errors(VALID[kind][1], msgpack.packb(value, use_bin_type=True))


@SETTINGS
@given(kind=st.sampled_from(sorted(VALID)), data=st.binary(max_size=512))
def test_arbitrary_bytes(kind, data):
    _only_protocol_errors(VALID[kind][1], data)


@SETTINGS
@given(kind=st.sampled_from(sorted(VALID)), data=st.data(), value=st.one_of(values, arrays))
def test_one_field_replaced(kind, data, value):
    payload, decode = VALID[kind]
    msg = msgpack.unpackb(payload, raw=False)
    key = data.draw(st.sampled_from(sorted(msg) + ["unknown_field"]))
    msg[key] = value
    _only_protocol_errors(decode, msgpack.packb(msg, use_bin_type=True))


@SETTINGS
@given(kind=st.sampled_from(sorted(VALID)), data=st.data())
def test_truncated_or_flipped(kind, data):
    payload, decode = VALID[kind]
    cut = data.draw(st.integers(0, len(payload) - 1))
    try:
        decode(payload[:cut])
        raise AssertionError("a truncated message was accepted")
    except ProtocolError:
        pass
    flipped = bytearray(payload)
    i = data.draw(st.integers(0, len(payload) - 1))
    flipped[i] ^= data.draw(st.integers(1, 255))
    _only_protocol_errors(decode, bytes(flipped))


@SETTINGS
@given(n=st.integers(1, 40), scale=st.floats(-1e3, 1e3), horizon=st.integers(1, 64))
def test_valid_transitions_round_trip(n, scale, horizon):
    rng = np.random.default_rng(n)
    b = TransitionBatch("x", 0, 0, scale * rng.normal(size=(n, OBS)), rng.uniform(-1, 1, (n, ACT)),
                        scale * rng.normal(size=n), rng.normal(size=(n, OBS)), np.zeros(n, bool), np.ones(n, bool),
                        horizon=np.full(n, horizon), privileged=rng.uniform(-50, 50, (n, PRIV)),
                        next_privileged=rng.uniform(-50, 50, (n, PRIV)))
    back = decode_transitions(encode_transitions(b, DEFAULT_LIMITS), obs_dim=OBS, act_dim=ACT, priv_dim=PRIV)
    assert back.n == n and np.array_equal(back.horizon, b.horizon)
    assert np.allclose(back.privileged, b.privileged.astype(np.float32))
