"""Wire protocol: round trips, and every malformed message raising ProtocolError (nothing else)."""

from __future__ import annotations

import threading

import msgpack
import numpy as np
import pytest

from forcegrasp.protocol import (
    PROTOCOL_VERSION,
    REASONS,
    Checkpoint,
    Keys,
    Limits,
    ProtocolError,
    RejectCounter,
    Stats,
    TransitionBatch,
    Weights,
    decode_checkpoint,
    decode_stats,
    decode_transitions,
    decode_weights,
    encode_checkpoint,
    encode_stats,
    encode_transitions,
    encode_weights,
    message_type,
    validate_name,
)

OBS, ACT = 77, 7


def make_batch(n: int = 64, seed: int = 0, episodes: int = 0) -> TransitionBatch:
    rng = np.random.default_rng(seed)
    batch = TransitionBatch(
        actor_id="actor-1", seq=5, policy_version=3,
        obs=rng.standard_normal((n, OBS)).astype(np.float32),
        action=rng.uniform(-1, 1, (n, ACT)).astype(np.float32),
        reward=rng.standard_normal(n).astype(np.float32),
        next_obs=rng.standard_normal((n, OBS)).astype(np.float32),
        terminated=rng.random(n) < 0.1, truncated=rng.random(n) < 0.05,
    )
    if episodes:
        batch.episode_returns = rng.standard_normal(episodes).astype(np.float32)
        batch.episode_lengths = rng.integers(1, 200, episodes).astype(np.int32)
        batch.episode_successes = rng.random(episodes) < 0.5
    return batch


def make_weights() -> Weights:
    rng = np.random.default_rng(1)
    params = {"pi.0.weight": rng.standard_normal((256, OBS)).astype(np.float32),
              "pi.0.bias": np.zeros(256, np.float32), "obs_count": np.array(7, np.int64)}
    return Weights(policy_version=4, step=1200, params=params, meta={"hidden": [256, 256], "obs_dim": OBS})


def raw(payload: bytes) -> dict:
    return msgpack.unpackb(payload, raw=False)


def pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def decode_batch(payload, **kw):
    return decode_transitions(payload, obs_dim=OBS, act_dim=ACT, **kw)


def assert_rejected(payload, reason: str | None = None, decoder=decode_batch, **kw) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        decoder(payload, **kw)
    assert info.value.reason in REASONS
    if reason is not None:
        assert info.value.reason == reason, str(info.value)
    return info.value


# --------------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("n, episodes", [(1, 0), (64, 0), (256, 3)])
def test_transition_round_trip(n, episodes):
    batch = make_batch(n, episodes=episodes)
    got = decode_batch(encode_transitions(batch))
    assert (got.actor_id, got.seq, got.policy_version, got.n) == ("actor-1", 5, 3, n)
    for name in ("obs", "action", "reward", "next_obs", "terminated", "truncated"):
        np.testing.assert_array_equal(getattr(got, name), getattr(batch, name))
    assert got.obs.dtype == np.float32 and got.terminated.dtype == np.bool_
    assert got.time == pytest.approx(batch.time)
    if episodes:
        np.testing.assert_array_equal(got.episode_returns, batch.episode_returns)
        np.testing.assert_array_equal(got.episode_lengths, batch.episode_lengths)
        np.testing.assert_array_equal(got.episode_successes, batch.episode_successes)
    else:
        assert not got.has_episodes


def test_decoded_arrays_are_zero_copy_views():
    got = decode_batch(encode_transitions(make_batch()))
    assert not got.obs.flags.writeable and not got.obs.flags.owndata


def test_encoder_casts_to_wire_dtypes():
    batch = make_batch(8)
    batch.obs = batch.obs.astype(np.float64)
    batch.next_obs = batch.next_obs.astype(">f4")  # big-endian input still travels little-endian
    batch.terminated = batch.terminated.astype(np.int64)
    got = decode_batch(encode_transitions(batch))
    assert got.obs.dtype == np.float32 and got.next_obs.dtype.str == "<f4"
    assert got.terminated.dtype == np.bool_


def test_third_party_flags_as_uint8_are_accepted():
    msg = raw(encode_transitions(make_batch(4)))
    msg["terminated"] = {"dtype": "|u1", "shape": [4], "data": bytes([0, 1, 0, 1])}
    got = decode_batch(pack(msg))
    assert got.terminated.tolist() == [False, True, False, True]


def test_weights_round_trip_and_expected_shapes():
    w = make_weights()
    payload = encode_weights(w)
    expected = {k: v.shape for k, v in w.params.items()}
    got = decode_weights(payload, expected=expected)
    assert (got.policy_version, got.step, got.meta) == (4, 1200, w.meta)
    for name, value in w.params.items():
        np.testing.assert_array_equal(got.params[name], value)
        assert got.params[name].dtype == value.dtype
    assert len(payload) < sum(v.nbytes for v in w.params.values()) + 512  # raw bytes, no bloat
    assert_rejected(payload, "shape", decode_weights, expected={**expected, "pi.0.bias": (128,)})
    assert_rejected(payload, "shape", decode_weights, expected={"pi.0.weight": (256, OBS)})


def test_stats_and_checkpoint_round_trip():
    stats = Stats("learner", "0", {"updates_per_s": 41.5, "steps": 1000, "loss": float("nan"),
                                   "per_actor": {"a0": np.float32(1500.0)}, "ok": True})
    got = decode_stats(encode_stats(stats))
    assert got.values == {"updates_per_s": 41.5, "steps": 1000, "loss": None,
                          "per_actor": {"a0": 1500.0}, "ok": True}
    ckpt = Checkpoint(step=20000, path="runs/x/ckpt/step_20000.safetensors", policy_version=9,
                      metrics={"success_rate": 0.6, "return": -3.5})
    got = decode_checkpoint(encode_checkpoint(ckpt))
    assert (got.step, got.path, got.policy_version, got.metrics) == (20000, ckpt.path, 9, ckpt.metrics)
    assert message_type(encode_checkpoint(ckpt)) == "checkpoint"


# --------------------------------------------------------------------------------------------
# Malformed messages, one class at a time
# --------------------------------------------------------------------------------------------

def mutated(**changes) -> bytes:
    msg = raw(encode_transitions(make_batch(16)))
    for key, value in changes.items():
        if value is None:
            del msg[key]
        else:
            msg[key] = value
    return pack(msg)


def test_wrong_version():
    assert_rejected(mutated(v=PROTOCOL_VERSION + 1), "version")
    assert_rejected(mutated(v="1"), "version")
    assert_rejected(mutated(v=True), "version")
    assert_rejected(mutated(v=None), "version")


def test_wrong_type():
    assert_rejected(mutated(t="weights"), "type")
    assert_rejected(encode_weights(make_weights()), "type")
    assert_rejected(encode_transitions(make_batch()), "type", decode_weights)


@pytest.mark.parametrize("dtype", ["<f8", "<f2", "|O", "<U4", "V4", "bogus", 7])
def test_bad_dtype(dtype):
    msg = raw(encode_transitions(make_batch(16)))
    msg["obs"]["dtype"] = dtype
    assert_rejected(pack(msg), "dtype")


def test_object_dtype_is_never_allowed_in_weights():
    msg = raw(encode_weights(make_weights()))
    msg["params"]["pi.0.bias"]["dtype"] = "|O8"
    assert_rejected(pack(msg), "dtype", decode_weights)


def test_truncated_payload():
    payload = encode_transitions(make_batch(16))
    for cut in (1, 10, len(payload) // 2, len(payload) - 1):
        assert_rejected(payload[:cut], "malformed")


def test_truncated_array_data():
    msg = raw(encode_transitions(make_batch(16)))
    msg["obs"]["data"] = msg["obs"]["data"][:-4]
    assert_rejected(pack(msg), "shape")


@pytest.mark.parametrize("field, shape", [
    ("obs", [15, OBS]), ("obs", [16, OBS + 1]), ("action", [16, ACT + 1]), ("reward", [16, 1]),
    ("next_obs", [16, 76]), ("terminated", [15]),
])
def test_shape_mismatch(field, shape):
    msg = raw(encode_transitions(make_batch(16)))
    dtype = np.dtype(msg[field]["dtype"])
    msg[field] = {"dtype": dtype.str, "shape": shape, "data": bytes(int(np.prod(shape)) * dtype.itemsize)}
    assert_rejected(pack(msg), "shape")


def test_expected_dims_are_enforced():
    payload = encode_transitions(make_batch(4))
    assert_rejected(payload, "shape", decode_transitions, obs_dim=53, act_dim=ACT)
    assert_rejected(payload, "shape", decode_transitions, obs_dim=OBS, act_dim=6)


@pytest.mark.parametrize("shape", [[-1], [1.5], ["3"], [True], [1] * 9, "16"])
def test_bad_shape_values(shape):
    msg = raw(encode_transitions(make_batch(16)))
    msg["reward"]["shape"] = shape
    assert_rejected(pack(msg), "shape")


def test_huge_shape_product_is_rejected_before_allocating():
    msg = raw(encode_transitions(make_batch(16)))
    msg["obs"]["shape"] = [2**62, 2**62]
    assert_rejected(pack(msg), "shape")


def test_empty_batch_and_episode_stats_mismatch():
    msg = raw(encode_transitions(make_batch(4, episodes=2)))
    msg["ep_length"] = {"dtype": "<i4", "shape": [1], "data": bytes(4)}
    assert_rejected(pack(msg), "shape")
    msg = raw(encode_transitions(make_batch(4, episodes=2)))
    del msg["ep_success"]
    assert_rejected(pack(msg), "missing_field")
    empty = {name: {"dtype": spec["dtype"], "shape": [0, *spec["shape"][1:]], "data": b""}
             for name, spec in raw(encode_transitions(make_batch(4))).items() if isinstance(spec, dict)}
    assert_rejected(pack(raw(encode_transitions(make_batch(4))) | empty), "shape")


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("field", ["obs", "action", "reward", "next_obs"])
def test_non_finite_values(field, value):
    batch = make_batch(8)
    getattr(batch, field).flat[3] = value
    with pytest.raises(ProtocolError) as info:  # the sender refuses too
        encode_transitions(batch)
    assert info.value.reason == "nonfinite"
    msg = raw(encode_transitions(make_batch(8)))
    arr = np.frombuffer(msg[field]["data"], np.float32).copy()
    arr[3] = value
    msg[field]["data"] = arr.tobytes()
    assert_rejected(pack(msg), "nonfinite")


def test_non_finite_weights_and_metadata():
    msg = raw(encode_weights(make_weights()))
    bias = np.zeros(256, np.float32)
    bias[0] = np.nan
    msg["params"]["pi.0.bias"]["data"] = bias.tobytes()
    assert_rejected(pack(msg), "nonfinite", decode_weights)
    msg = raw(encode_weights(make_weights()))
    msg["meta"] = {"lr": float("inf")}
    assert_rejected(pack(msg), "nonfinite", decode_weights)


def test_invalid_boolean_bytes():
    msg = raw(encode_transitions(make_batch(4)))
    msg["truncated"]["data"] = bytes([0, 2, 0, 0])
    assert_rejected(pack(msg), "bad_field")
    msg["truncated"]["dtype"] = "|u1"
    assert_rejected(pack(msg), "bad_field")


def test_oversize_payload():
    payload = encode_transitions(make_batch(64))
    assert_rejected(payload, "oversize", limits=Limits(max_payload_bytes=len(payload) - 1))
    assert_rejected(b"\x00" * (65 * 1024 * 1024), "oversize")
    assert_rejected(payload, "shape", limits=Limits(max_batch=32))


@pytest.mark.parametrize("payload", [
    pack([1, 2, 3]), pack("transitions"), pack(None), pack(42), pack(b"bytes"), pack(1.5),
])
def test_non_map_payload(payload):
    assert_rejected(payload, "not_a_map")


@pytest.mark.parametrize("payload", [b"", "a string", None, 12, [1], bytearray(b"\xc1")])
def test_not_bytes_or_empty(payload):
    assert_rejected(payload, "malformed")


def test_trailing_bytes_and_msgpack_limits():
    assert_rejected(encode_transitions(make_batch(4)) + b"\x00", "malformed")
    assert_rejected(pack({"v": 1, "t": "x", "k": "s" * 100_000}), "malformed")      # max_str_len
    assert_rejected(pack({"v": 1, "t": "x", "k": list(range(5000))}), "malformed")   # max_array_len
    assert_rejected(pack({1: 2}), "malformed")                                        # non-string key
    assert_rejected(b"\x81\xa1v\xd6\xff\x00\x00\x00\x01", "malformed")               # ext (timestamp)
    assert_rejected(b"\x81\xa1v\xa2\xff\xfe", "malformed")                            # invalid UTF-8


def test_missing_and_extra_fields():
    assert_rejected(mutated(obs=None), "missing_field")
    assert_rejected(mutated(seq=None), "missing_field")
    payload = mutated(colour="blue")
    assert_rejected(payload, "extra_field")
    assert decode_batch(payload, limits=Limits(allow_extra_fields=True)).seq == 5


@pytest.mark.parametrize("changes", [
    {"seq": -1}, {"seq": 2**64 - 1}, {"seq": 1.0}, {"seq": True}, {"policy_version": "3"},
    {"actor": "a/b"}, {"actor": "*"}, {"actor": ""}, {"actor": 3.5}, {"time": "now"},
    {"obs": [1, 2, 3]}, {"obs": {"dtype": "<f4", "shape": [16, OBS]}},
])
def test_bad_scalar_fields(changes):
    assert_rejected(mutated(**changes))


def test_deeply_nested_junk():
    depth = 100_000
    assert_rejected(b"\x91" * depth + b"\xc0", "malformed")             # arrays beyond msgpack's stack
    assert_rejected(b"\x81\xa1a" * depth + b"\xc0", "malformed")        # maps likewise
    nested: dict = {}
    cursor = nested
    for _ in range(200):                                              # within msgpack, beyond our depth
        cursor["x"] = {}
        cursor = cursor["x"]
    msg = raw(encode_weights(make_weights()))
    msg["meta"] = nested
    assert_rejected(pack(msg), "bad_field", decode_weights)
    assert_rejected(pack({"v": 1, "t": "stats", "service": "s", "id": "0", "values": nested}), "bad_field", decode_stats)


def test_stats_values_must_be_numbers():
    base = {"v": PROTOCOL_VERSION, "t": "stats", "service": "learner", "id": "0"}
    assert_rejected(pack(base | {"values": {"a": "text"}}), "bad_field", decode_stats)
    assert_rejected(pack(base | {"values": {"a": [1, 2]}}), "bad_field", decode_stats)
    assert_rejected(pack(base | {"values": {"a": float("nan")}}), "nonfinite", decode_stats)
    assert_rejected(pack(base | {"values": [1]}), "bad_field", decode_stats)
    with pytest.raises(ProtocolError):
        encode_stats(Stats("learner", "0", {"a": "text"}))


DECODERS = [decode_batch, decode_weights, decode_stats, decode_checkpoint, message_type]


def test_random_bytes_fuzz():
    rng = np.random.default_rng(1234)
    for i in range(3000):
        size = int(rng.integers(0, 300))
        payload = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        if i % 3 == 0 and payload:  # start like a map so decoding goes deeper than the first byte
            payload = b"\x8f" + payload
        for decoder in DECODERS:
            with pytest.raises(ProtocolError):
                decoder(payload)


def test_mutation_fuzz_of_valid_messages():
    """Overwrite bytes of real messages: decoding either succeeds or raises ProtocolError."""
    rng = np.random.default_rng(99)
    valid = [(encode_transitions(make_batch(4, episodes=1)), decode_batch),
             (encode_weights(Weights(1, 2, {"w": np.ones((3, 2), np.float32)}, {"a": [1, "x"]})), decode_weights),
             (encode_stats(Stats("actor", "1", {"a": 1.0, "b": {"c": 2}})), decode_stats),
             (encode_checkpoint(Checkpoint(1, "/p", 1, {"r": 1.0})), decode_checkpoint)]
    outcomes = {"ok": 0, "rejected": 0}
    for payload, decoder in valid:
        for _ in range(1500):
            data = bytearray(payload)
            for _ in range(int(rng.integers(1, 4))):
                data[int(rng.integers(0, len(data)))] = int(rng.integers(0, 256))
            try:
                decoder(bytes(data))
                outcomes["ok"] += 1
            except ProtocolError:
                outcomes["rejected"] += 1
    assert outcomes["rejected"] > 1000 and outcomes["ok"] > 0


# --------------------------------------------------------------------------------------------
# Keys and counters
# --------------------------------------------------------------------------------------------

def test_keys():
    keys = Keys("exp1")
    assert keys.transitions("actor-0") == "forcegrasp/exp1/transitions/actor-0"
    assert keys.transitions(3) == "forcegrasp/exp1/transitions/3"
    assert keys.all_transitions == "forcegrasp/exp1/transitions/*"
    assert keys.weights == "forcegrasp/exp1/weights"
    assert keys.weights_latest == "forcegrasp/exp1/weights/latest"
    assert keys.checkpoints == "forcegrasp/exp1/checkpoints"
    assert keys.best == "forcegrasp/exp1/best"
    assert keys.stats("learner", 0) == "forcegrasp/exp1/stats/learner/0"
    assert keys.alive("actor", "a1") == "forcegrasp/exp1/alive/actor/a1"
    assert keys.alive_of("actor") == "forcegrasp/exp1/alive/actor/*"
    assert keys.parse_alive("forcegrasp/exp1/alive/actor/a1") == ("actor", "a1")
    assert keys.parse_stats(keys.stats("evaluator", "e")) == ("evaluator", "e")
    assert keys.actor_of(keys.transitions("a7")) == "a7"
    with pytest.raises(ProtocolError):
        keys.parse_alive("forcegrasp/other/alive/actor/a1")
    with pytest.raises(ProtocolError):
        keys.actor_of("forcegrasp/exp1/weights")


@pytest.mark.parametrize("name", ["", "a*b", "$x", "a/b", "a#", "what?", "two words", "tab\t", "x" * 129, None, 1.5, True])
def test_invalid_names(name):
    with pytest.raises(ProtocolError):
        validate_name(name)
    if isinstance(name, str):
        with pytest.raises(ProtocolError):
            Keys(name)


def test_reject_counter_is_thread_safe():
    counter = RejectCounter()

    def work():
        for i in range(2000):
            counter.reject(ProtocolError("shape" if i % 2 else "dtype", "x"))
            counter.accept()

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert counter.counts() == {"shape": 4000, "dtype": 4000}
    assert counter.total == 8000 and counter.accepted == 8000
    assert counter.reject("oversize") == 1 and counter.last_error == "oversize"


def test_service_loop_counts_and_drops():
    """What a receiver does: decode, count rejects by reason, keep going."""
    counter = RejectCounter()
    payloads = [encode_transitions(make_batch(4)), b"junk", mutated(v=9), pack([1]),
                encode_transitions(make_batch(4))]
    kept = []
    for payload in payloads:
        try:
            kept.append(decode_batch(payload))
            counter.accept()
        except ProtocolError as err:
            counter.reject(err)
    assert len(kept) == 2 and counter.counts() == {"malformed": 1, "version": 1, "not_a_map": 1}
