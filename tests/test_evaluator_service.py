"""The evaluator as a real process: following checkpoints announced over Zenoh, serving the best
policy (Zenoh and HTTP) as it changes, bad requests, and ``kill -9`` at any moment.

The test plays the learner: it listens on the learner's endpoint, writes policy files into the
run's checkpoints folder and announces them on ``forcegrasp/<run>/checkpoints``. Policies have
known scores (constant-speed policies, see ``test_evaluator.py``): the best five of a set of
speeds are the five slowest, whatever the evaluator computes. Every process is started here and
ended here, by PID.
"""

from __future__ import annotations

import http.client
import json
import os
import re
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from forcegrasp.protocol import Checkpoint, Keys, decode_stats, encode_checkpoint
from forcegrasp import topk
from forcegrasp.protocol.best import decode_best
from forcegrasp_evaluator.endpoint import BestFetchError, fetch_best_http, fetch_best_zenoh
from forcegrasp_evaluator.evaluator import CRASH_ENV
from forcegrasp.transport import (
    QueueSubscriber,
    close_session,
    declare_publisher,
    free_tcp_port,
    open_session,
    wait_for_subscribers,
)

from test_evaluator import policy_bytes, tiny_config, write_checkpoint

TIMEOUT = 60.0


def start_evaluator(config_path: Path, log: Path, *args: str, env: dict | None = None) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "forcegrasp_evaluator", "--config", str(config_path), *args]
    return subprocess.Popen(cmd, stdout=open(log, "ab"), stderr=subprocess.STDOUT,
                            env={**os.environ, **(env or {})})


def stop(proc: subprocess.Popen) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


class Harness:
    def __init__(self, tmp_path):
        self.tmp = tmp_path
        self.port = free_tcp_port()
        self.config = tiny_config(tmp_path, run="evrun", **{
            "network.learner_listen": f'["tcp/127.0.0.1:{self.port}"]', "network.lease_ms": "1000"})
        self.config_path = tmp_path / "evaluator.toml"
        self.config_path.write_text(self.config.to_toml())
        self.keys = Keys("evrun")
        self.session = open_session([f"tcp/127.0.0.1:{self.port}"], [])
        self.stats_sub = QueueSubscriber(self.session, self.keys.all_stats, maxsize=4096, put_timeout=0.0)
        self.announce = declare_publisher(self.session, self.keys.checkpoints)
        self.latest: dict = {}
        self.log = tmp_path / "evaluator.log"
        # --all: every checkpoint of the burst below is evaluated (the default follows the front)
        self.proc = start_evaluator(self.config_path, self.log, "--scan-every", "1000", "--stats-every", "0.3", "--all")

    def publish(self, step: int, speed: float) -> None:
        path = write_checkpoint(self.config, step, policy_bytes(self.config, step, speed))
        self.announce.put(encode_checkpoint(Checkpoint(step, f"/elsewhere/on/the/learner/{path.name}", step // 1000)))

    def wait_for(self, what, predicate, timeout=TIMEOUT):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            payload = self.stats_sub.get(timeout=0.1)
            if payload is not None:
                s = decode_stats(payload)
                if s.service == "evaluator":
                    self.latest = s.values
            assert self.proc.poll() is None, "evaluator died: " + self.log.read_text()[-3000:]
            if self.latest and predicate(self.latest):
                return self.latest
        raise AssertionError(f"timed out waiting for {what}; stats {self.latest}; log {self.log.read_text()[-2000:]}")

    def index(self) -> dict:
        return topk.check_folder(Path(self.config.run.output_dir) / "evrun" / "evaluator" / "top", k=5)

    def close(self) -> int:
        code = stop(self.proc)
        self.stats_sub.close()
        close_session(self.session)
        return code


def get(port, path, method="GET"):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request(method, path)
        resp = conn.getresponse()
        return resp.status, resp.read()
    finally:
        conn.close()


def test_process_follows_announced_checkpoints_and_serves_the_best(tmp_path, capsys):
    from forcegrasp.cli import main as cli

    h = Harness(tmp_path)
    try:
        h.wait_for("the evaluator up", lambda s: s["http_port"] is not None)
        assert wait_for_subscribers(h.announce, timeout=20)
        port = h.latest["http_port"]
        status, body = get(port, "/best")
        assert status == 503  # nothing evaluated yet, and it says so
        reply = next(iter(h.session.get(h.keys.best, timeout=5)))
        assert reply.err is not None and "no checkpoint evaluated yet" in reply.err.payload.to_bytes().decode()

        speeds = {1000: 0.5, 2000: 0.9, 3000: 0.2, 4000: 0.7, 5000: 0.4, 6000: 0.8, 7000: 0.3}
        for step, speed in speeds.items():
            h.publish(step, speed)
        h.announce.put(b"\x93junk")  # hostile or broken announcements: counted, dropped
        h.announce.put(encode_checkpoint(Checkpoint(8000, "/etc/passwd")))
        s = h.wait_for("7 evaluations", lambda s: s["evaluations"] == 7 and s["rejected"] >= 2)
        assert s["rejected_by_reason"] == {"malformed": 1, "bad_field": 1}
        index = h.index()
        slowest = sorted(speeds, key=speeds.get)[:5]
        assert sorted(m["step"] for m in index["members"]) == sorted(slowest)
        assert index["best"] == topk.policy_file_name(3000)
        assert s["best_step"] == 3000 and sorted(map(int, s["top_scores"])) == sorted(slowest)

        def served_over_zenoh():
            best = fetch_best_zenoh(h.session, "evrun", timeout=5)
            member = next(m for m in h.index()["members"] if m["best"])
            assert best.sha256 == member["sha256"] and best.step == member["step"]
            path = Path(h.config.run.output_dir) / "evrun" / "evaluator" / "top" / member["file"]
            assert best.policy == path.read_bytes()
            assert (best.object, best.force_feedback) == ("camera", True)
            assert best.score == pytest.approx(member["rank_score"]) and best.episodes == 3
            return best

        def served_over_http():
            status, body = get(port, "/best")
            assert status == 200
            meta = json.loads(body)
            best = fetch_best_http(f"http://127.0.0.1:{port}", run="evrun")
            assert best.sha256 == meta["sha256"]
            return meta["step"], best

        assert served_over_zenoh().step == 3000 and served_over_http()[0] == 3000

        # A better checkpoint arrives: the endpoints follow.
        h.publish(9000, 0.05)
        h.wait_for("the new best", lambda s: s["evaluations"] == 8 and s["best_step"] == 9000)
        assert served_over_zenoh().step == 9000 and served_over_http()[0] == 9000
        assert sorted(m["step"] for m in h.index()["members"]) == sorted([9000, 3000, 7000, 5000, 1000])

        # Bad requests get clear errors.
        replies = list(h.session.get(h.keys.best + "?format=xml", timeout=5))
        assert len(replies) == 1 and replies[0].err is not None
        assert "takes no parameters" in json.loads(replies[0].err.payload.to_bytes())["error"]
        with pytest.raises(BestFetchError, match="no evaluator answered.*unknown run 'nosuchrun'"):
            fetch_best_zenoh(h.session, "nosuchrun", timeout=1.5)
        for path in ("/../../etc/passwd", "/best/..%2f..%2findex.json", "//evaluator/top/index.json", "/top/index.json"):
            status, body = get(port, path)
            assert status == 404 and json.loads(body)["error"]
        assert get(port, "/best", "DELETE")[0] == 405
        assert get(port, "/best?run=nosuchrun")[0] == 404

        # ... and the service keeps serving.
        assert decode_best(next(iter(h.session.get(h.keys.best, timeout=5))).ok.payload.to_bytes()).step == 9000
        assert get(port, "/best/policy")[0] == 200

        # forcegrasp best: over Zenoh (through the learner's endpoint) and over HTTP.
        out = tmp_path / "best.safetensors"
        assert cli(["best", "--out", str(out), "--config", str(h.config_path)]) == 0
        assert out.read_bytes() == served_over_zenoh().policy
        assert json.loads(capsys.readouterr().out)["step"] == 9000
        out2 = tmp_path / "best-http.safetensors"
        assert cli(["best", "--out", str(out2), "--url", f"http://127.0.0.1:{port}"]) == 0
        assert out2.read_bytes() == out.read_bytes()
        capsys.readouterr()
        missing = tmp_path / "never.safetensors"
        assert cli(["best", "--out", str(missing), "--config", str(h.config_path), "--set", "run.name=nosuchrun",
                    "--timeout", "1.5"]) == 1
        err = capsys.readouterr().err
        assert "no evaluator answered" in err and "Evaluators are running for: evrun" in err
        assert cli(["best", "--out", str(missing), "--url", f"http://127.0.0.1:{port}", "--set", "run.name=x"]) == 1
        assert "unknown run 'x'" in capsys.readouterr().err
        # A queryable that answers junk: the client refuses it and writes nothing.
        fake = h.session.declare_queryable(Keys("fakerun").best, lambda q: q.reply(Keys("fakerun").best, b"\x81\xa1v\x01"))
        assert cli(["best", "--out", str(missing), "--config", str(h.config_path), "--set", "run.name=fakerun"]) == 1
        assert "malformed reply" in capsys.readouterr().err
        fake.undeclare()
        assert not missing.exists()

        # 7 queries reached it (1 before any evaluation, 5 served, 1 malformed), 6 HTTP 404s.
        s = h.wait_for("query counts", lambda s: s["queries"] >= 7 and s["http_requests"].get("404", 0) >= 6)
        assert s["bad_queries"] == 2 and s["http_requests"]["405"] == 1
    finally:
        code = h.close()
    assert code == 0, h.log.read_text()[-2000:]  # SIGINT: a clean stop


def test_kill9_at_any_moment_keeps_a_consistent_top_five(tmp_path):
    """A burst of checkpoints on disk; the evaluator is SIGKILLed right after writing a new
    member's file (before its index), right after an index (before deleting the evicted file),
    and at random moments while it works; each time the folder must be consistent, and the run,
    restarted, must end exactly as if nothing had happened."""
    config = tiny_config(tmp_path, run="crash", **{"network.learner_listen": f'["tcp/127.0.0.1:{free_tcp_port()}"]'})
    config_path = tmp_path / "crash.toml"
    config_path.write_text(config.to_toml())
    seed = int(os.environ.get("FORCEGRASP_TEST_SEED", time.time_ns() % 10**6))
    rng = random.Random(seed)
    # Mostly improving, with setbacks: the top five changes at most checkpoints.
    order = [0.9, 0.85, 0.8, 0.95, 0.75, 0.7, 0.99, 0.6, 0.5, 0.97, 0.4, 0.3, 0.45, 0.2, 0.92, 0.25, 0.15, 0.88,
             0.1, 0.35]
    speeds = {1000 * (i + 1): v for i, v in enumerate(order)}
    for step, speed in speeds.items():
        write_checkpoint(config, step, policy_bytes(config, step, speed))
    folder = Path(config.run.output_dir) / "crash" / "evaluator" / "top"
    log = tmp_path / "crash.log"

    def check_after_crash():
        if not (folder / "index.json").exists():
            return None
        index = topk.check_folder(folder, k=5)  # every named file complete and verified
        evaluated = {h["step"]: h["score"] for h in index["history"]}
        assert len(evaluated) == len(index["history"]), "a checkpoint recorded twice"
        best_five = sorted(evaluated, key=lambda s: (-evaluated[s], s))[:5]
        assert sorted(m["step"] for m in index["members"]) == sorted(best_five)
        return index

    def named():
        return {m["file"] for m in json.loads((folder / "index.json").read_text())["members"]}

    def peek():  # while a process runs: the index only (its files may be replaced under our feet)
        return json.loads((folder / "index.json").read_text())

    procs = []

    def launch(**env):
        procs.append(start_evaluator(config_path, log, "--all", env=env))
        return procs[-1]

    try:
        # Deterministic crash points (the run resumes where the previous one died):
        # 3rd admission = step 3000's file written, its index not; 4th index = step 6000's, which
        # evicts step 4000 (0.95) whose file is still there; then step 9000's file before its index.
        for point, leftover in (("policy_written:3", 3000), ("index_written:4", 4000), ("policy_written:2", 9000)):
            proc = launch(**{CRASH_ENV: point})
            assert proc.wait(timeout=TIMEOUT) == -signal.SIGKILL, log.read_text()[-2000:]
            check_after_crash()
            assert (folder / topk.policy_file_name(leftover)).exists()
            assert topk.policy_file_name(leftover) not in named()
        # Random moments while it works: wait for its next commit, then kill within half a second.
        kills = 0
        for _ in range(3):
            before = len(check_after_crash()["history"])
            proc = launch()
            deadline = time.monotonic() + TIMEOUT
            while len(peek()["history"]) == before and time.monotonic() < deadline:
                assert proc.poll() is None, log.read_text()[-2000:]
                time.sleep(0.02)
            time.sleep(rng.uniform(0.0, 0.5))
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
            kills += 1
            check_after_crash()
        proc = launch()
        deadline = time.monotonic() + TIMEOUT
        while peek()["last_step"] != max(speeds) and time.monotonic() < deadline:
            assert proc.poll() is None, log.read_text()[-2000:]
            time.sleep(0.3)
        # If the last run had already finished everything, the index is complete at once: wait
        # until the new process has its signal handlers (it logs its start line after that), or
        # a SIGINT during its imports would kill it instead of stopping it cleanly.
        while len(re.findall(r"evaluator \S+: run ", log.read_text())) < len(procs) and time.monotonic() < deadline:
            assert proc.poll() is None, log.read_text()[-2000:]
            time.sleep(0.1)
        assert stop(proc) == 0
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    index = check_after_crash()
    assert sorted(h["step"] for h in index["history"]) == sorted(speeds), f"seed {seed}"  # each exactly once
    slowest = sorted(speeds, key=speeds.get)[:5]
    assert sorted(m["step"] for m in index["members"]) == sorted(slowest), f"seed {seed}"
    assert index["best"] == topk.policy_file_name(slowest[0])
    assert sorted(p.name for p in folder.iterdir()) == sorted(["index.json"] + [topk.policy_file_name(s) for s in slowest])
    assert kills == 3
