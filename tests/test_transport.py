"""Zenoh transport between real processes on loopback: transitions, queries, liveliness.

Each test spawns its helper process with ``sys.executable -c``, finds a free port by binding port
0, bounds every wait with a timeout and kills its processes by PID in ``finally``.
"""

from __future__ import annotations

import queue
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from forcegrasp import transport
from forcegrasp.protocol import (
    Keys,
    ProtocolError,
    decode_transitions,
    decode_weights,
    encode_weights,
)

RUN = "transport-test"
OBS, ACT = 77, 7

# Shared by the helper process and the test, so both sides build identical batches.
SHARED = textwrap.dedent("""
    import numpy as np
    from forcegrasp.protocol import TransitionBatch, Weights

    def batch_for(seq, n=64):
        rng = np.random.default_rng(seq)
        return TransitionBatch(
            actor_id="actor-0", seq=seq, policy_version=seq // 10,
            obs=rng.standard_normal((n, 77), dtype=np.float32),
            action=rng.uniform(-1, 1, (n, 7)).astype(np.float32),
            reward=rng.standard_normal(n, dtype=np.float32),
            next_obs=rng.standard_normal((n, 77), dtype=np.float32),
            terminated=rng.random(n) < 0.05, truncated=np.zeros(n, bool), time=float(seq))

    def weights_v(version):
        rng = np.random.default_rng(version)
        return Weights(policy_version=version, step=100 * version, time=float(version),
                       params={"pi.0.weight": rng.standard_normal((256, 77), dtype=np.float32)})
""")

PUBLISHER = SHARED + textwrap.dedent("""
    import sys
    from forcegrasp import transport
    from forcegrasp.protocol import Keys, encode_transitions
    endpoint, count = sys.argv[1], int(sys.argv[2])
    keys = Keys("transport-test")
    with transport.open_session([], [endpoint]) as session:
        assert transport.wait_for_peers(session, 1, timeout=20), "no peer"
        pub = transport.declare_publisher(session, keys.transitions("actor-0"))
        assert transport.wait_for_subscribers(pub, timeout=20), "no subscriber"
        for seq in range(count):
            pub.put(encode_transitions(batch_for(seq)))
        print("SENT", count, flush=True)
        input()  # stay until the test closes stdin, so nothing is cut off in flight
""")

SERVER = SHARED + textwrap.dedent("""
    import sys, time
    from forcegrasp import transport
    from forcegrasp.protocol import Keys, encode_weights
    endpoint = sys.argv[1]
    keys = Keys("transport-test")
    cached = encode_weights(weights_v(7))
    session = transport.open_session([endpoint], [])
    transport.declare_queryable(session, keys.weights_latest, lambda: cached)
    token = transport.declare_token(session, keys.alive("learner", "0"))
    print("READY", flush=True)
    time.sleep(120)  # killed by the test
""")

shared_ns: dict = {}
exec(SHARED, shared_ns)
batch_for, weights_v = shared_ns["batch_for"], shared_ns["weights_v"]


def spawn(code: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code, *map(str, args)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def kill(proc: subprocess.Popen | None) -> None:
    """SIGKILL by PID and reap; safe to call twice."""
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)


def wait_line(proc: subprocess.Popen, expected: str, timeout: float = 30.0) -> None:
    """Block until the helper prints ``expected`` (or fail with its stderr)."""
    deadline = time.monotonic() + timeout
    line = ""
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if line.startswith(expected):
            return
        if not line and proc.poll() is not None:
            break
    kill(proc)
    pytest.fail(f"helper did not print {expected!r}; last line {line!r}; stderr: {proc.stderr.read()[-2000:]}")


@pytest.fixture
def endpoint() -> str:
    return transport.tcp_endpoint("127.0.0.1", transport.free_tcp_port())


def test_transitions_between_processes_arrive_complete_and_in_order(endpoint):
    count = 300
    keys = Keys(RUN)
    session = transport.open_session([endpoint], [])
    proc = None
    try:
        sub = transport.QueueSubscriber(session, keys.all_transitions, maxsize=count, put_timeout=None, with_key=True)
        proc = spawn(PUBLISHER, endpoint, count)
        seqs = []
        deadline = time.monotonic() + 60
        while len(seqs) < count and time.monotonic() < deadline:
            item = sub.get(timeout=1.0)
            if item is None:
                assert proc.poll() is None, proc.stderr.read()
                continue
            key, payload = item
            batch = decode_transitions(payload, obs_dim=OBS, act_dim=ACT)
            assert keys.actor_of(key) == batch.actor_id == "actor-0"
            expected = batch_for(batch.seq)
            for name in ("obs", "action", "reward", "next_obs", "terminated", "truncated"):
                np.testing.assert_array_equal(getattr(batch, name), getattr(expected, name))
            assert batch.policy_version == expected.policy_version
            seqs.append(batch.seq)
        assert seqs == list(range(count)), "gaps or reordering"
        assert sub.dropped == 0
        wait_line(proc, "SENT")
    finally:
        kill(proc)
        transport.close_session(session)


def test_query_reply_and_liveliness_across_processes(endpoint):
    keys = Keys(RUN)
    events: queue.Queue = queue.Queue()
    session = transport.open_session([], [endpoint], lease_ms=1000)
    proc = None
    try:
        transport.watch_liveliness(session, keys.alive_of("learner"), lambda k, alive: events.put((k, alive)))
        proc = spawn(SERVER, endpoint)
        wait_line(proc, "READY")
        assert transport.wait_for_peers(session, 1, timeout=20)
        assert events.get(timeout=10) == (keys.alive("learner", "0"), True)

        payload = transport.query_bytes(session, keys.weights_latest, timeout=5)
        assert payload is not None
        got = decode_weights(payload, expected={"pi.0.weight": (256, OBS)})
        assert got.policy_version == 7
        np.testing.assert_array_equal(got.params["pi.0.weight"], weights_v(7).params["pi.0.weight"])
        assert transport.query_bytes(session, keys.best, timeout=0.5) is None  # nobody serves it

        killed_at = time.monotonic()
        kill(proc)
        assert events.get(timeout=10) == (keys.alive("learner", "0"), False)
        assert time.monotonic() - killed_at < 5
    finally:
        kill(proc)
        transport.close_session(session)


def test_peer_reconnects_when_the_listener_restarts(endpoint):
    """An actor's session outlives the learner: it reconnects by itself when it returns."""
    keys = Keys(RUN)
    session = transport.open_session([], [endpoint])
    proc = None
    try:
        assert not transport.wait_for_peers(session, 1, timeout=0.3)  # nobody there yet: silent
        for _ in range(2):
            proc = spawn(SERVER, endpoint)
            wait_line(proc, "READY")
            assert transport.wait_for_peers(session, 1, timeout=20)
            assert transport.query_bytes(session, keys.weights_latest, timeout=5) is not None
            kill(proc)
            deadline = time.monotonic() + 10
            while transport.connected_count(session) and time.monotonic() < deadline:
                time.sleep(0.02)
            assert transport.connected_count(session) == 0
    finally:
        kill(proc)
        transport.close_session(session)


def test_latest_subscriber_keeps_only_newest_weights(endpoint):
    keys = Keys(RUN)
    learner = transport.open_session([endpoint], [])
    actor = transport.open_session([], [endpoint])
    try:
        assert transport.wait_for_peers(actor, 1, timeout=10)
        latest = transport.subscribe_latest(actor, keys.weights)
        pub = transport.declare_publisher(learner, keys.weights)
        assert transport.wait_for_subscribers(pub, timeout=10)
        assert transport.take_latest(latest) is None
        for version in range(1, 6):
            pub.put(encode_weights(weights_v(version)))
        time.sleep(0.3)
        payload = transport.wait_latest(latest, timeout=5)
        assert decode_weights(payload).policy_version == 5
        assert transport.take_latest(latest) is None  # older ones were dropped, not queued
    finally:
        transport.close_session(actor)
        transport.close_session(learner)


def test_queue_subscriber_drops_and_counts_when_full(endpoint):
    receiver = transport.open_session([endpoint], [])
    sender = transport.open_session([], [endpoint])
    try:
        assert transport.wait_for_peers(sender, 1, timeout=10)
        sub = transport.QueueSubscriber(receiver, "forcegrasp/x/*", maxsize=2, put_timeout=0)
        pub = transport.declare_publisher(sender, "forcegrasp/x/y")
        assert transport.wait_for_subscribers(pub, timeout=10)
        for i in range(10):
            pub.put(bytes([i]))
        deadline = time.monotonic() + 5
        while sub.received < 10 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert (sub.received, sub.dropped, sub.queue.qsize()) == (10, 8, 2)
        assert [sub.get(1), sub.get(1), sub.get(0.05)] == [b"\x00", b"\x01", None]
        sub.close()
    finally:
        transport.close_session(sender)
        transport.close_session(receiver)


def test_bad_payloads_from_the_wire_are_rejected_not_raised(endpoint):
    """A receiver's loop sees only ProtocolError for junk arriving over Zenoh."""
    receiver = transport.open_session([endpoint], [])
    sender = transport.open_session([], [endpoint])
    try:
        assert transport.wait_for_peers(sender, 1, timeout=10)
        sub = transport.QueueSubscriber(receiver, Keys(RUN).all_transitions)
        pub = transport.declare_publisher(sender, Keys(RUN).transitions("evil"))
        assert transport.wait_for_subscribers(pub, timeout=10)
        for junk in (b"", b"\xc1", b"\x91" * 5000, encode_weights(weights_v(1))):
            pub.put(junk)
        for _ in range(4):
            with pytest.raises(ProtocolError):
                decode_transitions(sub.get(timeout=5), obs_dim=OBS, act_dim=ACT)
    finally:
        transport.close_session(sender)
        transport.close_session(receiver)


def test_documented_third_party_client_joins(endpoint):
    """The client in docs/protocol.md (plain zenoh + msgpack) is accepted by our decoder."""
    doc = (Path(__file__).resolve().parent.parent / "docs" / "protocol.md").read_text()
    code = re.findall(r"```python\n(.*?)```", doc, re.S)[-1].replace('"tcp/127.0.0.1:7447"', repr(endpoint))
    keys = Keys("default")
    session = transport.open_session([endpoint], [])
    proc = None
    try:
        served = encode_weights(weights_v(3))
        transport.declare_queryable(session, keys.weights_latest, lambda: served)
        sub = transport.QueueSubscriber(session, keys.all_transitions, with_key=True)
        events: queue.Queue = queue.Queue()
        transport.watch_liveliness(session, keys.alive_of("actor"), lambda k, alive: events.put(alive))
        proc = spawn(code)
        seen = []
        deadline = time.monotonic() + 60
        while len(seen) < 10 and time.monotonic() < deadline:
            item = sub.get(timeout=1.0)
            if item is not None:
                batch = decode_transitions(item[1], obs_dim=OBS, act_dim=ACT)
                assert keys.actor_of(item[0]) == batch.actor_id == "remote-0"
                seen.append((batch.seq, batch.policy_version))
        assert seen == [(seq, 3) for seq in range(10)]
        assert proc.wait(timeout=30) == 0, proc.stderr.read()
        assert [events.get(timeout=10), events.get(timeout=10)] == [True, False]
    finally:
        kill(proc)
        transport.close_session(session)


def test_config_builder_sets_endpoints_and_lease():
    config = transport.make_config(["tcp/127.0.0.1:7000"], ["tcp/127.0.0.1:7001"], lease_ms=1500,
                                   extra={"adminspace/enabled": False})
    assert '"peer"' in config.get_json("mode")
    assert "7000" in config.get_json("listen/endpoints")
    assert "7001" in config.get_json("connect/endpoints")
    assert config.get_json("scouting/multicast/enabled") == "false"
    assert config.get_json("transport/link/tx/lease") == "1500"
    assert transport.tcp_endpoint("::1", 7447) == "tcp/[::1]:7447"


# A service session at the project's settings (network.shared_memory): the receiver reports its
# shared-memory resident size (RssShmem) whenever asked; each sender publishes 256 KiB messages.
SHM_RECEIVER = textwrap.dedent("""
    import sys
    from forcegrasp.config import load_config
    from forcegrasp.runtime import open_service_session
    from forcegrasp.transport import QueueSubscriber
    endpoint, shm = sys.argv[1], sys.argv[2]
    config = load_config(env={}, overrides=[f'network.learner_listen=["{endpoint}"]', f"network.shared_memory={shm}"])
    session = open_service_session(config, "learner")
    inbox = QueueSubscriber(session, "shm-test/**", maxsize=10_000)
    print("READY", flush=True)
    received = 0
    for line in sys.stdin:
        while inbox.get(timeout=0.5) is not None:
            received += 1
        kb = [int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("RssShmem:")][0]
        print("SHM", kb, received, flush=True)
""")

SHM_SENDER = textwrap.dedent("""
    import sys
    from forcegrasp.config import load_config
    from forcegrasp.runtime import open_service_session
    from forcegrasp import transport
    endpoint, shm = sys.argv[1], sys.argv[2]
    config = load_config(env={}, overrides=[f'network.connect=["{endpoint}"]', f"network.shared_memory={shm}"])
    session = open_service_session(config, "actor")
    assert transport.wait_for_peers(session, 1, timeout=20)
    pub = transport.declare_publisher(session, "shm-test/x")
    assert transport.wait_for_subscribers(pub, timeout=20)
    for i in range(20):
        pub.put(bytes([i % 251]) * (256 * 1024))
    print("SENT", flush=True)
    input()
""")


def receiver_shm_after_senders(endpoint: str, shm: bool, senders: int = 3) -> list[tuple[int, int]]:
    """(RssShmem kB, messages received) of one receiver after each of ``senders`` sender processes
    (one after another, each SIGKILLed when done, as a churned actor)."""
    receiver = spawn(SHM_RECEIVER, endpoint, str(shm).lower())
    out = []
    try:
        wait_line(receiver, "READY")
        for _ in range(senders):
            sender = spawn(SHM_SENDER, endpoint, str(shm).lower())
            try:
                wait_line(sender, "SENT")
                time.sleep(1.0)
            finally:
                kill(sender)
            time.sleep(1.0)
            receiver.stdin.write("?\n")
            receiver.stdin.flush()
            line = receiver.stdout.readline().split()
            out.append((int(line[1]), int(line[2])))
    finally:
        kill(receiver)
    return out


def test_actor_restarts_leave_no_shared_memory_in_the_learner():
    """The soak found the learner growing ~16 MB per actor restart: Zenoh's shared memory (on by
    default) keeps each sender's segment mapped in the receiver after the sender exits
    (eclipse-zenoh/zenoh#2787). Services therefore run with it off (network.shared_memory)."""
    endpoint = transport.tcp_endpoint("127.0.0.1", transport.free_tcp_port())
    off = receiver_shm_after_senders(endpoint, shm=False)
    assert [n for _, n in off] == [20, 40, 60], off  # every message arrived
    assert off[-1][0] < 4096, f"shared memory mapped with network.shared_memory = false: {off}"
    # The control: with it on, the same three senders leave their segments behind. If Zenoh fixes
    # #2787 this part fails, and shared memory can be reconsidered.
    endpoint = transport.tcp_endpoint("127.0.0.1", transport.free_tcp_port())
    shm_dir = Path("/dev/shm")
    before = set(shm_dir.glob("*.zenoh"))
    try:
        on = receiver_shm_after_senders(endpoint, shm=True)
    finally:  # the SIGKILLed senders could not remove their segments: this test's own, by name
        for leftover in set(shm_dir.glob("*.zenoh")) - before:
            leftover.unlink(missing_ok=True)
    assert [n for _, n in on] == [20, 40, 60], on
    # At least two of the three exited senders' ~16 MB segments stay mapped (one sender in a fresh
    # clone's run was seen to add none: it may have sent over TCP before shared memory was set up).
    assert on[-1][0] >= 2 * 16 * 1024 - 1024, f"expected ~16 MB mapped per exited sender: {on}"
