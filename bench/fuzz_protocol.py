"""Bounded fuzz run of every message decoder and of the evaluator's HTTP page.

    python bench/fuzz_protocol.py --messages 100000 --http 5000

Each message starts from a valid transitions (with n-step horizons and privileged state),
weights, stats, checkpoint or best message and gets one random mutation: a field replaced by a
random value (nil, numbers at and past the int64 edges, NaN, strings, huge declared array
shapes, wrong dtypes, truncated array data), an unknown field, the payload cut short, bytes
flipped, or random bytes. A decoder may accept (the mutation was harmless) or raise
ProtocolError; any other exception is a bug and is printed with the message that caused it.

``--http N`` then sends N mutated requests to a live `EvaluatorHTTPServer` over raw sockets
(methods, paths with '..', '//', escapes and NUL bytes, huge or negative Content-Length, header
floods, truncated requests, random bytes), each from one of the 254 loopback addresses 127.0.0.x
so that the per-client rate limit does not answer them all. It counts the statuses the server
answered (its own counts: the client often sees the connection reset before a 400 arrives); a
bug is a 500 (an exception in a handler), or the page not answering a valid request afterwards.
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import socket
import sys
import time
import tracemalloc

import msgpack
import numpy as np

from forcegrasp.protocol import (Checkpoint, Progress, ProtocolError, Stats, TransitionBatch, Weights, decode_checkpoint,
                                 decode_progress, decode_stats, decode_transitions, decode_weights, encode_checkpoint,
                                 encode_progress, encode_stats, encode_transitions, encode_weights)
from forcegrasp.protocol.best import BestPolicy, decode_best, encode_best


def valid_messages() -> dict:
    rng = np.random.default_rng(0)
    n = 16
    batch = TransitionBatch("a", 1, 2, rng.normal(size=(n, 77)), rng.uniform(-1, 1, (n, 7)), rng.normal(size=n),
                            rng.normal(size=(n, 77)), np.zeros(n, bool), np.zeros(n, bool),
                            np.zeros(2, np.float32), np.ones(2, np.int32), np.ones(2, bool), horizon=np.full(n, 3),
                            privileged=rng.normal(size=(n, 14)), next_privileged=rng.normal(size=(n, 14)))
    from forcegrasp.policy import Actor, Policy
    from forcegrasp.task import policy_metadata

    meta = policy_metadata("mug", True, (8, 8))
    policy_bytes = Policy.from_actor(Actor(77, 7, (8, 8)), meta).to_bytes()
    best = BestPolicy(run="r", step=2000, score=1.0, success_rate=0.5, episodes=100, eval_score=1.0,
                      eval_success_rate=0.5, eval_episodes=10, object="mug", force_feedback=True, policy_version=3,
                      sha256=hashlib.sha256(policy_bytes).hexdigest(), policy=policy_bytes)
    return {
        "transitions": (encode_transitions(batch), lambda p: decode_transitions(p, obs_dim=77, act_dim=7, priv_dim=14)),
        "weights": (encode_weights(Weights(3, 10, {"w": np.ones((4, 3), np.float32)}, meta={"k": 1})),
                    lambda p: decode_weights(p, expected={"w": (4, 3)})),
        "stats": (encode_stats(Stats("learner", "0", {"a": 1.0, "b": {"c": 2}})), decode_stats),
        "checkpoint": (encode_checkpoint(Checkpoint(2000, "policy-000002000.safetensors", 3)), decode_checkpoint),
        "progress": (encode_progress(Progress(500, 120, 33.0, {"actor-0": (9, 4)})), decode_progress),
        "best": (encode_best(best), decode_best),
    }


def random_value(rng: np.random.Generator):
    kind = rng.integers(12)
    if kind == 0:
        return None
    if kind == 1:
        return [-1, 0, 2**63 - 1, 2**63, 2**64 - 1, -2**63][int(rng.integers(6))]
    if kind == 2:
        return [np.nan, np.inf, -np.inf, 1e308, -0.0][int(rng.integers(5))]
    if kind == 3:
        return "x" * int(rng.integers(0, 70000))
    if kind == 4:
        return bytes(rng.integers(0, 256, int(rng.integers(0, 64)), dtype=np.uint8))
    if kind == 5:
        return [random_value(rng) for _ in range(int(rng.integers(0, 4)))]
    if kind == 6:
        return {str(i): random_value(rng) for i in range(int(rng.integers(0, 4)))}
    dtype = str(rng.choice(["<f4", "<f8", "|u1", "|b1", "<i4", "<i8", "O", "<U8", ">f4"]))
    shape = [[0, 1, 3, 16, 77, 2**31, 2**62, -1][int(rng.integers(8))] for _ in range(int(rng.integers(0, 4)))]
    data = bytes(rng.integers(0, 256, int(rng.integers(0, 512)), dtype=np.uint8))
    if kind == 7:  # NaN floats of a plausible shape
        data = np.full(16 * 77, np.nan, np.float32).tobytes()
        dtype, shape = "<f4", [16, 77]
    return {"dtype": dtype, "shape": shape, "data": data}


def mutate(payload: bytes, rng: np.random.Generator) -> bytes:
    kind = rng.integers(5)
    if kind == 0:  # cut short
        return payload[: int(rng.integers(0, len(payload)))]
    if kind == 1:  # flip bytes
        b = bytearray(payload)
        for _ in range(int(rng.integers(1, 5))):
            b[int(rng.integers(0, len(b)))] ^= int(rng.integers(1, 256))
        return bytes(b)
    if kind == 2:
        return bytes(rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8))
    msg = msgpack.unpackb(payload, raw=False)
    key = str(rng.choice(sorted(msg))) if kind == 3 else f"extra_{int(rng.integers(100))}"
    msg[key] = random_value(rng)
    return msgpack.packb(msg, use_bin_type=True)


HTTP_METHODS = ["GET", "HEAD", "POST", "PUT", "DELETE", "OPTIONS", "TRACE", "CONNECT", "get", "G\x00T", "X" * 300]
HTTP_PATHS = ["/", "/best", "/best/policy", "/top", "/best/../top", "//best", "/%2e%2e/etc/passwd", "/best?run=x",
              "/best%00", "http://evil/best", "*", "/" + "a" * 9000, "/\xff\xfe", "/best/policy/x", ""]


def http_request(rng: np.random.Generator) -> bytes:
    """One mutated HTTP request (raw bytes)."""
    kind = int(rng.integers(6))
    if kind == 0:
        return bytes(rng.integers(0, 256, int(rng.integers(1, 2000)), dtype=np.uint8))
    method, path = str(rng.choice(HTTP_METHODS)), str(rng.choice(HTTP_PATHS))
    version = str(rng.choice(["HTTP/1.1", "HTTP/1.0", "HTTP/9.9", "", "HTTP/1.1 extra"]))
    headers = ["Host: x"]
    if kind == 1:
        headers.append(f"Content-Length: {rng.choice(['-1', '99999999999', 'abc', '10', str(2**63)])}")
    if kind == 2:
        headers += [f"X-{i}: {'v' * int(rng.integers(1, 200))}" for i in range(int(rng.integers(50, 200)))]
    req = (f"{method} {path} {version}\r\n" + "\r\n".join(headers) + "\r\n\r\n").encode("utf-8", "surrogateescape")
    if kind == 3:
        req += bytes(rng.integers(0, 256, int(rng.integers(1, 5000)), dtype=np.uint8))  # an unannounced body
    if kind == 4:
        req = req[: int(rng.integers(1, len(req)))]  # cut short, then the client closes
    return req


def send_raw(port: int, source: str, data: bytes) -> str:
    """Send ``data`` from ``source``, close the write side, return the status code ('closed' if none)."""
    with socket.create_connection(("127.0.0.1", port), timeout=5, source_address=(source, 0)) as sock:
        try:
            sock.sendall(data)
            sock.shutdown(socket.SHUT_WR)
            line = sock.makefile("rb").readline(200)
        except OSError:
            return "closed"
    parts = line.split()
    return parts[1].decode("ascii", "replace") if len(parts) >= 2 and parts[0].startswith(b"HTTP/") else "closed"


def fuzz_http(n: int, rng: np.random.Generator) -> int:
    """Mutated requests against a live HTTP page; returns the number of bugs."""
    from forcegrasp_evaluator.endpoint import EvaluatorHTTPServer, Snapshot

    server = EvaluatorHTTPServer("127.0.0.1", 0, lambda: Snapshot.build("fuzz", None, {"members": []})).start()
    statuses: collections.Counter = collections.Counter()
    bugs, t0 = 0, time.perf_counter()
    try:
        for i in range(n):
            status = send_raw(server.port, f"127.0.0.{1 + i % 254}", http_request(rng))
            statuses[status] += 1
        after = send_raw(server.port, "127.0.0.1", b"GET /top HTTP/1.1\r\nHost: x\r\n\r\n")
        if after != "200":
            bugs += 1
            print(f"BUG http: a valid request after the fuzz got {after}", file=sys.stderr)
    finally:
        server.stop()
    bugs += server.requests_by_status.get("500", 0)
    print(f"\nHTTP: {n} requests in {time.perf_counter() - t0:.1f} s; bugs {bugs}; the server answered "
          + ", ".join(f"{k}: {v}" for k, v in sorted(server.requests_by_status.items()))
          + "; the client read " + ", ".join(f"{k}: {v}" for k, v in sorted(statuses.items())))
    return bugs


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--http", type=int, default=0, help="mutated requests against a live HTTP page (0: none)")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    valid = valid_messages()
    kinds = sorted(valid)
    counts: dict[str, collections.Counter] = {k: collections.Counter() for k in kinds}
    bugs = 0
    tracemalloc.start()
    t0 = time.perf_counter()
    for i in range(args.messages):
        kind = kinds[i % len(kinds)]
        payload, decode = valid[kind]
        bad = mutate(payload, rng)
        try:
            decode(bad)
            counts[kind]["accepted"] += 1
        except ProtocolError as exc:
            counts[kind][exc.reason] += 1
        except Exception as exc:  # noqa: BLE001 (that is the point)
            bugs += 1
            if bugs <= 5:
                print(f"BUG {kind}: {type(exc).__name__}: {exc}\n  payload {bad[:200]!r}", file=sys.stderr)
        if (i + 1) % 20000 == 0:
            print(f"{i + 1} messages, {bugs} bugs, {time.perf_counter() - t0:.0f} s", flush=True)
    current, peak = tracemalloc.get_traced_memory()
    print(f"\n{args.messages} messages in {time.perf_counter() - t0:.1f} s; non-ProtocolError exceptions: {bugs}; "
          f"traced memory now {current / 2**20:.1f} MiB, peak {peak / 2**20:.1f} MiB")
    reasons = sorted({r for c in counts.values() for r in c} - {"accepted"})
    print("| message | accepted | " + " | ".join(reasons) + " |")
    print("|---" * (len(reasons) + 2) + "|")
    for kind in kinds:
        print(f"| {kind} | {counts[kind]['accepted']} | " + " | ".join(str(counts[kind][r]) for r in reasons) + " |")
    if args.http:
        bugs += fuzz_http(args.http, rng)
    return 1 if bugs else 0


if __name__ == "__main__":
    raise SystemExit(main())
