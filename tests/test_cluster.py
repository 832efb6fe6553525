"""End to end: real learner and actor processes over Zenoh on loopback, at tiny settings.

One cluster serves the tests of this module in order: streaming without gaps, weights reaching
the actors, kill -9 and restart of an actor, malformed messages, kill -9 and restart of the
learner. Every process is started here and ended here, by PID.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from forcegrasp.config import load_config
from forcegrasp.protocol import Keys, ProtocolError, TransitionBatch, decode_stats, encode_transitions
from forcegrasp.transport import QueueSubscriber, close_session, declare_publisher, free_tcp_port, open_session

TIMEOUT = 90.0


class Cluster:
    def __init__(self, tmp_path):
        self.tmp = tmp_path
        self.port = free_tcp_port()
        self.run = "e2e"
        self.config_path = tmp_path / "cluster.toml"
        config = load_config(
            overrides=[
                f"run.name={self.run}",
                f"run.output_dir={tmp_path / 'runs'}",
                "env.object=camera",
                "actor.envs_per_actor=2",
                "actor.random_steps=100",
                "actor.publish_batch=16",
                f'network.learner_listen=["tcp/127.0.0.1:{self.port}"]',
                "network.lease_ms=1000",
                "learner.broadcast_every=25",
                "learner.max_lead=64",
                "learner.checkpoint_every=600",
                "evaluator.eval_every=250",
                "learner.stats_every_s=0.5",
                "learner.sac.learning_starts=200",
                "learner.sac.hidden=[32, 32]",
                "learner.sac.batch_size=32",
                "learner.sac.num_threads=1",
                "learner.recipe=paper",  # the rate-limit test below checks one update per step
            ]
        )
        self.config_path.write_text(config.to_toml())
        self.procs: dict[str, subprocess.Popen] = {}
        self.session = open_session([], [f"tcp/127.0.0.1:{self.port}"])
        self.stats_sub = QueueSubscriber(self.session, Keys(self.run).all_stats, maxsize=4096, put_timeout=0.0)
        self.latest: dict[str, dict] = {}
        self.history: dict[str, list[dict]] = {}
        self.sent_at: dict[str, list[float]] = {}  # the sender's clock, beside each history entry

    def start(self, name: str) -> subprocess.Popen:
        module = "forcegrasp_learner" if name == "learner" else "forcegrasp_actor"
        cmd = [sys.executable, "-m", module, "--config", str(self.config_path)]
        if name != "learner":
            cmd += ["--id", name, "--seed", str(sum(name.encode()))]
        log = open(self.tmp / f"{name}.log", "ab")
        self.procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
        return self.procs[name]

    def kill9(self, name: str) -> None:
        p = self.procs.pop(name)
        os.kill(p.pid, signal.SIGKILL)
        p.wait(timeout=10)
        self.latest.pop(name, None)

    def poll(self, seconds: float = 0.2) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            payload = self.stats_sub.get(timeout=0.05)
            if payload is None:
                continue
            s = decode_stats(payload)
            name = "learner" if s.service == "learner" else s.id
            self.latest[name] = s.values
            self.history.setdefault(name, []).append(s.values)
            self.sent_at.setdefault(name, []).append(s.time)

    def reports_since(self, name: str, t: float) -> list[dict]:
        """The stats `name` sent after wall time `t`: tells a restarted process from reports of
        its killed predecessor still in flight."""
        return [v for v, at in zip(self.history.get(name, []), self.sent_at.get(name, [])) if at >= t]

    def wait_for(self, what: str, predicate, timeout: float = TIMEOUT):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.poll()
            for name, p in self.procs.items():
                assert p.poll() is None, f"{name} died: " + (self.tmp / f"{name}.log").read_text()[-3000:]
            try:
                if predicate(self.latest):
                    return self.latest
            except (KeyError, TypeError):
                pass
        logs = {n: (self.tmp / f"{n}.log").read_text()[-1500:] for n in self.procs}
        raise AssertionError(f"timed out waiting for {what}; latest stats {self.latest}; logs {logs}")

    def close(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in self.procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.stats_sub.close()
        close_session(self.session)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    c = Cluster(tmp_path_factory.mktemp("cluster"))
    c.start("learner")
    c.start("actor-a")
    c.start("actor-b")
    try:
        yield c
    finally:
        c.close()


def test_two_actors_stream_without_gaps(cluster):
    s = cluster.wait_for(
        "both actors streaming and the learner training",
        lambda s: all(s["learner"]["actors"][a]["ingested"] >= 400 for a in ("actor-a", "actor-b"))
        and s["learner"]["updates"] > 50,
    )
    learner = s["learner"]
    assert learner["gaps"] == 0 and learner["rejected"] == 0
    # The rate limiter holds 1 update per step: the updates owed (update_debt) for whatever the
    # actors buffered before the learner came up are worked off (past MAX_UPDATE_DEBT they are
    # forgone, counted), then the debt stays within max_lead (+ what two actors can have in
    # flight), with the actors pausing; the counters agree: the gap between transitions and
    # updates grows no more than the debt may.
    limit = 64 + 2 * 4 * 16
    cluster.wait_for("the learner's lead worked off", lambda s: s["learner"]["update_debt"] <= limit)
    mark = len(cluster.history["learner"])
    start = cluster.history["learner"][mark - 1]
    s = cluster.wait_for("more training", lambda s: s["learner"]["updates"] > 400 + start["updates"])
    for values in cluster.history["learner"][mark:]:
        assert values["update_debt"] <= limit, values
        assert values["updates_forgone"] == start["updates_forgone"], values
        assert (values["ingested"] - values["updates"]) - (start["ingested"] - start["updates"]) <= limit, values
    assert any(a["paused_s"] > 0 for name, a in s.items() if name != "learner")
    for a in ("actor-a", "actor-b"):
        track = learner["actors"][a]
        assert track["gaps"] == 0 and track["duplicates"] == 0 and track["restarts"] == 0
        # Every batch 0..last_seq arrived: 16 transitions each.
        assert track["ingested"] == 16 * (track["last_seq"] + 1)


def test_weights_reach_the_actors(cluster):
    s = cluster.wait_for(
        "actors acting with broadcast weights",
        lambda s: s["actor-a"]["policy_version"] >= 3 and s["actor-b"]["policy_version"] >= 3,
    )
    acted_with = s["actor-a"]["policy_version"]  # a version the learner really broadcast:
    cluster.wait_for("learner stats catching up", lambda s: s["learner"]["policy_version"] >= acted_with)
    assert s["actor-a"]["rejected_weights"] == 0


def test_actor_kill9_and_restart_rejoins_with_current_weights(cluster):
    cluster.kill9("actor-a")
    updates_at_kill = cluster.latest["learner"]["updates"]
    cluster.wait_for("the learner training on without actor-a", lambda s: s["learner"]["updates"] > updates_at_kill + 25)
    restarted_at = time.time()
    cluster.start("actor-a")
    cluster.wait_for("actor-a back", lambda s: any(v["steps"] > 0 for v in cluster.reports_since("actor-a", restarted_at)))
    first = cluster.reports_since("actor-a", restarted_at)[0]
    # Its very first report already carries a learner policy: it asked weights/latest at start.
    assert first["policy_version"] >= 1
    cluster.wait_for(
        "actor-a's new stream ingested",
        lambda s: s["learner"]["actors"]["actor-a"]["restarts"] >= 1 and s["actor-a"]["sent_batches"] >= 3,
    )


def test_malformed_messages_are_counted_and_dropped(cluster):
    keys = Keys(cluster.run)
    pub = declare_publisher(cluster.session, keys.transitions("mallory"))
    good = TransitionBatch(
        actor_id="mallory", seq=0, policy_version=0,
        obs=np.zeros((4, 77), np.float32), action=np.zeros((4, 7), np.float32), reward=np.zeros(4, np.float32),
        next_obs=np.zeros((4, 77), np.float32), terminated=np.zeros(4, bool), truncated=np.zeros(4, bool),
    )
    wrong_dim = encode_transitions(TransitionBatch(**{**good.__dict__, "obs": np.zeros((4, 5), np.float32),
                                                      "next_obs": np.zeros((4, 5), np.float32)}))
    wrong_sender = encode_transitions(TransitionBatch(**{**good.__dict__, "actor_id": "actor-b"}))
    nan = bytearray(encode_transitions(good))
    junk = [b"", b"\x00\xff garbage", b"\x81\xa1v\x63", bytes(range(256)) * 10, wrong_dim, wrong_sender]
    with pytest.raises(ProtocolError):  # the encoder refuses NaN at the source ...
        encode_transitions(TransitionBatch(**{**good.__dict__, "reward": np.full(4, np.nan, np.float32)}))
    idx = bytes(nan).find(np.zeros(4, np.float32).tobytes())  # ... so forge one on the wire
    nan[idx : idx + 4] = np.float32(np.nan).tobytes()
    junk.append(bytes(nan))
    before = cluster.latest["learner"]["rejected"]
    ingested_before = cluster.latest["learner"]["ingested"]
    for payload in junk:
        pub.put(payload)
    s = cluster.wait_for("rejections counted", lambda s: s["learner"]["rejected"] >= before + len(junk))
    assert s["learner"]["rejected"] == before + len(junk)
    assert "mallory" not in s["learner"]["actors"]
    cluster.wait_for("ingestion continuing", lambda s: s["learner"]["ingested"] > ingested_before + 100)


def test_learner_kill9_and_restart_resumes_from_checkpoint(cluster):
    s = cluster.wait_for("a checkpoint", lambda s: s["learner"]["last_checkpoint"] >= 600)
    cluster.kill9("learner")
    time.sleep(1.0)
    restarted_at = time.time()
    cluster.start("learner")
    cluster.wait_for("the learner back", lambda s: cluster.reports_since("learner", restarted_at))
    first = cluster.reports_since("learner", restarted_at)[0]
    checkpoint = first["last_checkpoint"]
    assert checkpoint >= 600
    assert first["ingested"] >= checkpoint and first["replay_size"] >= checkpoint  # counter and replay continue
    cluster.wait_for(
        "actors streaming to the new learner",
        lambda s: s["learner"]["ingested"] > checkpoint + 200 and s["learner"]["updates"] > first["updates"],
    )
    # Between full checkpoints the learner leaves a policy snapshot for the evaluator every
    # evaluator.eval_every transitions (the paper tests every 2,000 steps).
    steps = sorted(int(p.stem.split("-")[1]) for p in (cluster.tmp / "runs" / cluster.run / "checkpoints").glob("policy-*"))
    # (A burst of backlog ingested in one loop, after a restart say, spaces two snapshots wider.)
    gaps = [b - a for a, b in zip(steps, steps[1:])]
    assert len(steps) >= 4 and float(np.median(gaps)) <= 300, steps
    # Actors kept their buffered batches while the learner was gone and never exited.
    assert all(p.poll() is None for n, p in cluster.procs.items() if n != "learner")
