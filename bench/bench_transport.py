"""Transport benchmark: transitions/s and weight-broadcast latency between two processes.

Two processes on loopback, as in a local run:

* throughput: a helper process plays an actor, encoding real-size TransitionBatch messages
  (obs 77, action 7) and publishing them reliably; this process plays the learner, receiving
  through the Zenoh callback -> queue path and fully decoding + validating every batch.  Measured
  over TCP only (``shared_memory=False``: what actors on other machines get) and with Zenoh's
  shared memory (processes on one host).
* weights latency: this process plays the learner, broadcasting a weights message of the real
  policy size; the helper (an actor) receives, decodes and validates each one.  One-way latency uses
  CLOCK_MONOTONIC, which is system-wide on Linux, so both processes read the same clock.  The
  helper also times the late-joiner path: ``get`` on ``weights/latest`` + decode.

Usage: ``python bench/bench_transport.py [--duration 3] [--batches 64 256] [--out REPORT.md]``
Prints the report (docs/benchmarks.md quotes its figures); ``--out`` also writes it to a file.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import textwrap
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import zenoh

from forcegrasp import transport
from forcegrasp.protocol import Keys, Weights, decode_transitions, encode_weights

OBS, ACT = 77, 7
ONE_ACTOR_RATE = 2000  # transitions/s one actor process produces at most (env benchmark)
GOAL = 50 * ONE_ACTOR_RATE
RUN = "bench"
REPO = Path(__file__).resolve().parent.parent
# The actor network of SACConfig's default (77 -> 256 -> 256 -> mean and log-std of 7): ~350 KB.
POLICY_SHAPES = {"pi.0.weight": (256, OBS), "pi.0.bias": (256,), "pi.1.weight": (256, 256),
                 "pi.1.bias": (256,), "pi.mu.weight": (ACT, 256), "pi.mu.bias": (ACT,),
                 "pi.log_std.weight": (ACT, 256), "pi.log_std.bias": (ACT,)}

HELPER = textwrap.dedent("""
    import json, sys, time
    import msgpack, numpy as np
    from forcegrasp import transport
    from forcegrasp.protocol import Keys, TransitionBatch, decode_weights, encode_transitions

    mode, endpoint, shm = sys.argv[1], sys.argv[2], sys.argv[3] == "1"
    keys = Keys("bench")
    session = transport.open_session([], [endpoint], shared_memory=shm)
    assert transport.wait_for_peers(session, 1, timeout=30), "no peer"

    def publish(batch_size, duration):
        rng = np.random.default_rng(0)
        n = batch_size
        batch = TransitionBatch(
            actor_id="actor-0", seq=0, policy_version=0,
            obs=rng.standard_normal((n, 77), dtype=np.float32),
            action=rng.uniform(-1, 1, (n, 7)).astype(np.float32),
            reward=rng.standard_normal(n, dtype=np.float32),
            next_obs=rng.standard_normal((n, 77), dtype=np.float32),
            terminated=np.zeros(n, bool), truncated=np.zeros(n, bool))
        pub = transport.declare_publisher(session, keys.transitions("actor-0"))
        assert transport.wait_for_subscribers(pub, timeout=30), "no subscriber"
        t0 = time.perf_counter()
        sent = 0
        while time.perf_counter() - t0 < duration:
            batch.seq = sent
            pub.put(encode_transitions(batch))   # real actor cost: encode + validate + send
            sent += 1
        elapsed = time.perf_counter() - t0
        session.put(keys.prefix + "/bench/end", msgpack.packb({"sent": sent, "elapsed": elapsed}))

    def weights(count):
        sub = transport.QueueSubscriber(session, keys.weights, maxsize=count + 8, put_timeout=None)
        session.put(keys.prefix + "/bench/ready", b"1")
        latencies = []
        while len(latencies) < count:
            payload = sub.get(timeout=30)
            assert payload is not None, "weights stopped arriving"
            w = decode_weights(payload)
            latencies.append((time.monotonic_ns() - w.meta["sent_ns"]) / 1e6)
        queries = []
        for _ in range(count):
            t0 = time.perf_counter()
            payload = transport.query_bytes(session, keys.weights_latest, timeout=5)
            decode_weights(payload)
            queries.append((time.perf_counter() - t0) * 1e3)
        print("RESULT " + json.dumps({"one_way_ms": latencies, "query_ms": queries}), flush=True)

    if mode == "pub":
        publish(int(sys.argv[4]), float(sys.argv[5]))
    else:
        weights(int(sys.argv[4]))
    time.sleep(0.5)
    transport.close_session(session)
""")


def spawn(*args: object) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", HELPER, *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def stop(proc: subprocess.Popen | None) -> None:
    """Kill the helper by PID if it is still running, and reap it."""
    if proc is not None and proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)


def bench_throughput(batch_size: int, duration: float, shm: bool) -> dict:
    """Transitions/s received, decoded and validated, from one publishing process."""
    import msgpack

    endpoint = transport.tcp_endpoint("127.0.0.1", transport.free_tcp_port())
    keys = Keys(RUN)
    session = transport.open_session([endpoint], [], shared_memory=shm)
    proc = None
    try:
        data = transport.QueueSubscriber(session, keys.all_transitions, maxsize=4096, put_timeout=None)
        control = transport.QueueSubscriber(session, keys.prefix + "/bench/end")
        proc = spawn("pub", endpoint, int(shm), batch_size, duration)
        received, expected_seq, gaps, first, last, end, size = 0, 0, 0, None, None, None, 0
        deadline = time.monotonic() + duration + 60
        while time.monotonic() < deadline and (end is None or received < end["sent"]):
            payload = data.get(timeout=0.2)
            if payload is None:
                end = end or _control(control, msgpack)
                if proc.poll() not in (None, 0):
                    raise RuntimeError(proc.stderr.read()[-2000:])
                continue
            batch = decode_transitions(payload, obs_dim=OBS, act_dim=ACT)
            size = len(payload)
            gaps += batch.seq != expected_seq
            expected_seq = batch.seq + 1
            received += 1
            first = first or time.perf_counter()
            last = time.perf_counter()
            end = end or _control(control, msgpack)
        if end is None or received < end["sent"]:
            raise RuntimeError(f"received {received} batches, helper reported {end}")
        elapsed = max(last - first, 1e-9)
        return {"batch": batch_size, "shm": shm, "batches": received, "gaps": gaps,
                "dropped": data.dropped, "recv_tps": (received - 1) * batch_size / elapsed,
                "send_tps": end["sent"] * batch_size / end["elapsed"],
                "mb_s": (received - 1) * size / elapsed / 1e6, "msg_bytes": size}
    finally:
        stop(proc)
        transport.close_session(session)


def _control(sub: transport.QueueSubscriber, msgpack) -> dict | None:
    payload = sub.get(timeout=0)
    return None if payload is None else msgpack.unpackb(payload)


def policy_weights(version: int, rng: np.random.Generator) -> Weights:
    params = {k: rng.standard_normal(shape).astype(np.float32) for k, shape in POLICY_SHAPES.items()}
    return Weights(policy_version=version, step=version * 100, params=params, meta={})


def bench_weights(count: int, shm: bool, interval: float = 0.02) -> dict:
    """One-way broadcast latency (encode excluded, decode included) and query round trip."""
    endpoint = transport.tcp_endpoint("127.0.0.1", transport.free_tcp_port())
    keys = Keys(RUN)
    rng = np.random.default_rng(0)
    session = transport.open_session([endpoint], [], shared_memory=shm)
    proc = None
    try:
        pub = transport.declare_publisher(session, keys.weights)
        ready = transport.QueueSubscriber(session, keys.prefix + "/bench/ready")
        latest = {"payload": encode_weights(policy_weights(0, rng))}
        transport.declare_queryable(session, keys.weights_latest, lambda: latest["payload"])
        proc = spawn("weights", endpoint, int(shm), count)
        if ready.get(timeout=60) is None:
            raise RuntimeError(proc.stderr.read()[-2000:] if proc.poll() is not None else "helper not ready")
        encode_ms = []
        for version in range(1, count + 1):
            w = policy_weights(version, rng)
            t0 = time.perf_counter()
            w.meta = {"sent_ns": time.monotonic_ns()}
            payload = encode_weights(w)
            encode_ms.append((time.perf_counter() - t0) * 1e3)
            w.meta["sent_ns"] = time.monotonic_ns()  # re-stamp: latency excludes encoding
            payload = encode_weights(w)
            latest["payload"] = payload
            pub.put(payload)
            time.sleep(interval)
        out, err = proc.communicate(timeout=120)
        line = next((l for l in out.splitlines() if l.startswith("RESULT ")), None)
        if line is None:
            raise RuntimeError(err[-2000:])
        result = json.loads(line[len("RESULT "):])
        return {"shm": shm, "bytes": len(payload), "encode_ms": float(np.median(encode_ms)),
                **{f"one_way_{k}": v for k, v in _percentiles(result["one_way_ms"]).items()},
                **{f"query_{k}": v for k, v in _percentiles(result["query_ms"]).items()}}
    finally:
        stop(proc)
        transport.close_session(session)


def _percentiles(values: list[float]) -> dict:
    a = np.asarray(values)
    return {"p50": float(np.percentile(a, 50)), "p90": float(np.percentile(a, 90)), "max": float(a.max())}


def decode_only_rate(batch_size: int, seconds: float = 1.0) -> float:
    """Upper bound for one receiving thread: decode + validate with no transport at all."""
    from forcegrasp.protocol import TransitionBatch, encode_transitions

    n = batch_size
    rng = np.random.default_rng(0)
    payload = encode_transitions(TransitionBatch(
        "a", 0, 0, rng.standard_normal((n, OBS), dtype=np.float32), np.zeros((n, ACT), np.float32),
        np.zeros(n, np.float32), rng.standard_normal((n, OBS), dtype=np.float32), np.zeros(n, bool),
        np.zeros(n, bool)))
    count, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        decode_transitions(payload, obs_dim=OBS, act_dim=ACT)
        count += 1
    return count * n / (time.perf_counter() - t0)


def render(throughput: list[dict], latency: list[dict], decode_rates: dict[int, float], duration: float) -> str:
    zenoh_version = _zenoh_version()
    lines = [
        "# Transport benchmark",
        "",
        f"Measured {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC by `python bench/bench_transport.py` on "
        f"{os.cpu_count()} CPU cores ({platform.processor() or platform.machine()}), Python "
        f"{platform.python_version()}, eclipse-zenoh {zenoh_version}, two processes on loopback "
        "(peer mode, reliable + blocking congestion control). Single runs on a shared machine "
        f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores when the report was written: "
        "other jobs were running), so expect sizeable run-to-run spread.",
        "",
        "## Transitions from one actor process to the learner",
        "",
        f"The helper encodes and validates real-size batches (obs 77, action 7) and publishes them for "
        f"{duration:g} s; the receiver goes through the Zenoh callback -> queue path and fully decodes "
        "and validates every batch (dtype, shapes, finite values). Goal: at least 50x one actor's "
        f"production (~{ONE_ACTOR_RATE:,} transitions/s), i.e. {GOAL:,} transitions/s.",
        "",
        "| batch | link | message | received transitions/s | sender transitions/s | MB/s | gaps | x one actor (goal 50) |",
        "|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in throughput:
        link = "shared memory" if r["shm"] else "TCP"
        lines.append(f"| {r['batch']} | {link} | {r['msg_bytes'] / 1024:.1f} KiB | {r['recv_tps']:,.0f} | "
                     f"{r['send_tps']:,.0f} | {r['mb_s']:.0f} | {r['gaps']} | {r['recv_tps'] / ONE_ACTOR_RATE:.0f} |")
    lines += ["", "Decode + validate alone (one thread, no transport): " + ", ".join(
        f"batch {b}: {rate:,.0f} transitions/s" for b, rate in decode_rates.items()) + ".", ""]
    lines += [
        "## Weights broadcast (real policy size)",
        "",
        "The learner publishes the actor network (77 -> 256 -> 256 -> 2 x 7, float32) every 20 ms; the "
        "actor process receives, decodes and validates it. One-way latency is from just before `put` to "
        "the end of decoding (CLOCK_MONOTONIC, shared by both processes); the query is the late-joiner "
        "path (`get` on `weights/latest`, reply from cached bytes, decode).",
        "",
        "| link | message | encode (learner) | one-way p50 | p90 | max | query round trip p50 | p90 | max |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in latency:
        link = "shared memory" if r["shm"] else "TCP"
        lines.append(
            f"| {link} | {r['bytes'] / 1024:.0f} KiB | {r['encode_ms']:.2f} ms | {r['one_way_p50']:.2f} ms | "
            f"{r['one_way_p90']:.2f} ms | {r['one_way_max']:.2f} ms | {r['query_p50']:.2f} ms | "
            f"{r['query_p90']:.2f} ms | {r['query_max']:.2f} ms |")
    lines.append("")
    return "\n".join(lines)


def _zenoh_version() -> str:
    try:
        from importlib.metadata import version

        return version("eclipse-zenoh")
    except Exception:
        return getattr(zenoh, "__version__", "?")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=3.0, help="seconds of publishing per throughput case")
    parser.add_argument("--batches", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--weights-count", type=int, default=100)
    parser.add_argument("--out", default=None, help="also write the report to this file")
    args = parser.parse_args(argv)

    throughput = []
    for shm in (False, True):
        for batch in args.batches:
            print(f"throughput: batch {batch}, {'shared memory' if shm else 'TCP'} ...", flush=True)
            r = bench_throughput(batch, args.duration, shm)
            print(f"  {r['recv_tps']:,.0f} transitions/s received ({r['recv_tps'] / ONE_ACTOR_RATE:.0f}x one actor), "
                  f"{r['batches']} batches, gaps {r['gaps']}", flush=True)
            throughput.append(r)
    decode_rates = {b: decode_only_rate(b) for b in args.batches}
    latency = []
    for shm in (False, True):
        print(f"weights latency: {'shared memory' if shm else 'TCP'} ...", flush=True)
        r = bench_weights(args.weights_count, shm)
        print(f"  {r['bytes'] / 1024:.0f} KiB: one-way p50 {r['one_way_p50']:.2f} ms, "
              f"query p50 {r['query_p50']:.2f} ms", flush=True)
        latency.append(r)
    report = render(throughput, latency, decode_rates, args.duration)
    print()
    print(report)
    if args.out:
        Path(args.out).write_text(report)
        print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
