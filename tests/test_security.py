"""The secure cluster, attacked on loopback: a real learner process with credentials (TLS, mutual
certificates, user/password, access control), and sessions that try to get in or overstep.

Each refusal is paired with the same action done right, so a test that cannot fail would show."""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh

from forcegrasp.certs import CertsError, make_credentials
from forcegrasp.config import ConfigError, load_config
from forcegrasp.protocol import (Checkpoint, Keys, TransitionBatch, decode_stats, decode_weights,
                                 encode_checkpoint, encode_transitions)
from forcegrasp.security import CredentialsError, access_control, credentials_folder, session_settings
from forcegrasp.transport import QueueSubscriber, close_session, free_tcp_port, open_session, query_bytes

RUN = "sec"
MARK = b"not-from-the-learner"


def _batch(actor_id: str, n: int = 16) -> TransitionBatch:
    rng = np.random.default_rng(0)
    return TransitionBatch(actor_id=actor_id, seq=0, policy_version=0, obs=rng.normal(size=(n, 77)),
                           action=rng.uniform(-1, 1, (n, 7)), reward=rng.normal(size=n),
                           next_obs=rng.normal(size=(n, 77)), terminated=np.zeros(n, bool),
                           truncated=np.zeros(n, bool))


class Secure:
    def __init__(self, tmp):
        self.tmp = tmp
        self.creds = tmp / "creds"
        make_credentials(self.creds, actors=2)
        make_credentials(tmp / "other-ca", actors=1)  # a valid-looking identity from another CA
        self.port = free_tcp_port()
        self.endpoint = f"tls/127.0.0.1:{self.port}"
        config = load_config(env={}, overrides=[
            f"run.name={RUN}", f"run.output_dir={tmp / 'runs'}", "env.object=camera", "learner.recipe=paper",
            f'network.learner_listen=["{self.endpoint}"]', f"network.credentials={self.creds}",
            "learner.stats_every_s=0.3", "learner.sac.learning_starts=100000", "learner.sac.hidden=[16, 16]"])
        self.config_path = tmp / "learner.toml"
        self.config_path.write_text(config.to_toml())
        self.log = open(tmp / "learner.log", "wb")
        self.learner = subprocess.Popen([sys.executable, "-m", "forcegrasp_learner", "--config", str(self.config_path)],
                                        stdout=self.log, stderr=subprocess.STDOUT)
        self.monitor = self.session("client", timeout_ms=60000)  # waits for the learner's router
        self.stats = QueueSubscriber(self.monitor, Keys(RUN).stats("learner", "0"), maxsize=1024, put_timeout=0.0)
        self.latest: dict = {}

    def session(self, identity: str, folder=None, timeout_ms: int = 3000, **changes) -> zenoh.Session:
        """A client session as `identity` from `folder` (default: the cluster's), with config
        values changed by `changes` (a wrong password, no certificate ...)."""
        settings = session_settings(folder or credentials_folder(self.creds, identity), "actor", RUN,
                                    connect_timeout_ms=timeout_ms)
        settings.update(changes)
        settings = {k: v for k, v in settings.items() if v is not None}
        mode = settings.pop("mode")
        return open_session([], [self.endpoint], mode=mode, extra=settings)

    def ingested(self, settle: float = 1.0) -> int:
        """The learner's count of accepted transitions, from its stats over `settle` seconds."""
        deadline = time.monotonic() + settle
        while time.monotonic() < deadline or not self.latest:
            assert self.learner.poll() is None, (self.tmp / "learner.log").read_text()[-3000:]
            payload = self.stats.get(timeout=0.1)
            if payload is not None:
                self.latest = decode_stats(payload).values
            if time.monotonic() > deadline + 30:
                raise AssertionError("no stats from the learner")
        return int(self.latest["ingested"])

    def close(self):
        self.stats.close()
        close_session(self.monitor)
        self.learner.send_signal(signal.SIGINT)
        try:
            self.learner.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.learner.kill()
            self.learner.wait()
        self.log.close()


@pytest.fixture(scope="module")
def secure(tmp_path_factory):
    cluster = Secure(tmp_path_factory.mktemp("secure"))
    try:
        yield cluster
    finally:
        cluster.close()


def test_outsiders_get_no_session(secure, tmp_path):
    """No credentials, a wrong password, a certificate of another CA, plain TCP: no session, so
    nothing in and nothing out; the learner's count stays where it was."""
    before = secure.ingested()
    wrong_pw = tmp_path / "actor-0"
    shutil.copytree(secure.creds / "actor-0", wrong_pw)
    (wrong_pw / "password").write_text("guessed\n")
    attempts = {
        "no user": dict(identity="actor-0", **{"transport/auth/usrpwd/user": None,
                                               "transport/auth/usrpwd/password": None}),
        "wrong password": dict(identity="actor-0", folder=wrong_pw),
        "no certificate": dict(identity="actor-0", **{"transport/link/tls/connect_certificate": None,
                                                      "transport/link/tls/connect_private_key": None}),
        "other CA's certificate": dict(identity="actor-0", **{
            "transport/link/tls/connect_certificate": str(secure.tmp / "other-ca/actor-0/cert.pem"),
            "transport/link/tls/connect_private_key": str(secure.tmp / "other-ca/actor-0/key.pem")}),
    }
    for what, kw in attempts.items():
        with pytest.raises(zenoh.ZError):
            s = secure.session(kw.pop("identity"), **kw)
            close_session(s)  # only reached if the learner let it in
            raise AssertionError(f"{what}: got a session")
    with pytest.raises(zenoh.ZError):  # plain TCP to the TLS port
        open_session([], [f"tcp/127.0.0.1:{secure.port}"], mode="client",
                     extra={"connect/timeout_ms": 3000, "connect/exit_on_failure": True})
    assert secure.ingested() == before
    # The same door with the right keys: actor-0 is let in and its transitions count.
    s = secure.session("actor-0")
    try:
        s.put(Keys(RUN).transitions("actor-0"), encode_transitions(_batch("actor-0")))
        deadline = time.monotonic() + 20
        while secure.ingested(0.3) < before + 16 and time.monotonic() < deadline:
            pass
        assert secure.ingested() == before + 16
    finally:
        close_session(s)


def test_an_actor_may_not_speak_for_others_or_for_the_learner(secure):
    keys = Keys(RUN)
    actor0 = secure.session("actor-0")
    actor1 = secure.session("actor-1")
    evaluator = secure.session("evaluator")
    try:
        weights_seen, ckpts_seen = [], []
        actor1.declare_subscriber(keys.weights, lambda s: weights_seen.append(s.payload.to_bytes()))
        evaluator.declare_subscriber(keys.checkpoints, lambda s: ckpts_seen.append(s.payload.to_bytes()))
        # Weights are out to actors: the legitimate query is answered by the learner.
        reply = query_bytes(actor1, keys.weights_latest, timeout=5.0)
        assert reply is not None and decode_weights(reply).policy_version >= 0
        before = secure.ingested()
        time.sleep(0.5)
        actor0.put(keys.weights, MARK)
        actor0.put(keys.progress, MARK)
        actor0.put(keys.checkpoints, encode_checkpoint(Checkpoint(1, "/etc/passwd", 1)))
        actor0.put(keys.transitions("actor-1"), encode_transitions(_batch("actor-1")))  # another actor's stream
        actor0.declare_queryable(keys.best, lambda q: q.reply(q.key_expr, MARK))  # posing as the evaluator
        time.sleep(1.0)
        assert MARK not in weights_seen and not ckpts_seen
        assert secure.ingested() == before
        client = secure.session("client")
        try:
            assert query_bytes(client, keys.best, timeout=2.0) is None  # no evaluator runs: nobody answers
        finally:
            close_session(client)
        # An authenticated identity with another identity's certificate matches no subject.
        mixed = secure.session("actor-1", **{
            "transport/link/tls/connect_certificate": str(secure.creds / "actor-0/cert.pem"),
            "transport/link/tls/connect_private_key": str(secure.creds / "actor-0/key.pem")})
        try:
            mixed.put(keys.transitions("actor-1"), encode_transitions(_batch("actor-1")))
            mixed.put(keys.transitions("actor-0"), encode_transitions(_batch("actor-0")))
            assert query_bytes(mixed, keys.weights_latest, timeout=2.0) is None
        finally:
            close_session(mixed)
        time.sleep(0.5)
        assert secure.ingested() == before
        # Its own stream, under an id of its machine ("actor-0.<suffix>"), is accepted.
        actor0.put(keys.transitions("actor-0.b"), encode_transitions(_batch("actor-0.b", 8)))
        deadline = time.monotonic() + 20
        while secure.ingested(0.3) < before + 8 and time.monotonic() < deadline:
            pass
        assert secure.ingested() == before + 8
    finally:
        for s in (actor0, actor1, evaluator):
            close_session(s)


def test_credentials_errors_are_clear(tmp_path):
    with pytest.raises(ConfigError, match="must be tls/"):
        load_config(env={}, overrides=[f"network.credentials={tmp_path}"])
    with pytest.raises(CredentialsError, match="identities there: none"):
        credentials_folder(tmp_path, "actor-0")
    make_credentials(tmp_path / "c", actors=1)
    assert credentials_folder(tmp_path / "c", "actor-0.host7") == tmp_path / "c" / "actor-0"
    (tmp_path / "c" / "actor-0" / "key.pem").unlink()
    with pytest.raises(CredentialsError, match="lacks key.pem"):
        session_settings(tmp_path / "c" / "actor-0", "actor", RUN)
    with pytest.raises(CertsError, match="identity 'root'"):
        make_credentials(tmp_path / "c", add=("root",))


def test_access_control_table_gives_each_role_only_its_keys():
    acl = access_control("r", ["learner", "evaluator", "client", "actor-0"])
    assert acl["default_permission"] == "deny" and {s["id"] for s in acl["subjects"]} == {"evaluator", "client", "actor-0"}
    ingress = {r["id"]: r for r in acl["rules"] if r["flows"] == ["ingress"]}
    puts = [k for r in ingress.values() if "put" in r["messages"] for k in r["key_exprs"]]
    assert not [k for k in puts if k.endswith(("/weights", "/progress", "/checkpoints"))]
    assert [r["id"] for r in ingress.values() if "declare_queryable" in r["messages"]] == ["evaluator/3"]
    assert all(s["cert_common_names"] == s["usernames"] for s in acl["subjects"])


def test_secure_cluster_trains_and_serves_the_best_policy(tmp_path):
    """`forcegrasp up` with credentials: learner (TLS router, access control), two actors and the
    evaluator as clients train, the evaluator scores a checkpoint, and `forcegrasp best` with the
    client identity fetches the policy through the learner."""
    import re

    creds = tmp_path / "creds"
    make_credentials(creds, actors=2)
    endpoint = f"tls/127.0.0.1:{free_tcp_port()}"
    sets = [f"run.name={RUN}", f"run.output_dir={tmp_path}", "env.object=camera", f"network.credentials={creds}",
            f'network.learner_listen=["{endpoint}"]', "actor.envs_per_actor=2", "actor.random_steps=100",
            "actor.publish_batch=16", "learner.stats_every_s=0.5", "learner.checkpoint_every=600",
            "learner.sac.learning_starts=200", "learner.sac.hidden=[32, 32]", "learner.sac.batch_size=32",
            "evaluator.eval_every=250", "evaluator.eval_episodes=2", "evaluator.final_rank_episodes=2",
            "evaluator.http_port=0"]
    cmd = [sys.executable, "-m", "forcegrasp.cli", "up"] + [a for s in sets for a in ("--set", s)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    try:
        deadline = time.monotonic() + 150
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if re.search(r"best held-out \d+% \(step", line):
                break
        text = "".join(lines)
        assert re.search(r"env steps, \d+/s", text), text
        assert re.search(r"best held-out \d+% \(step", text), text  # the evaluator scored a checkpoint
        learner_log = (tmp_path / RUN / "logs" / "learner.log").read_text()
        for actor in ("actor-0", "actor-1"):  # both actors streamed through the TLS router
            assert re.search(rf"sending: .*\b{actor}\b", learner_log), learner_log[-2000:]
        out = tmp_path / "best.safetensors"
        best = subprocess.run([sys.executable, "-m", "forcegrasp.cli", "best", "--out", str(out), "--timeout", "20",
                               "--set", f"run.name={RUN}", "--set", f"network.credentials={creds}",
                               "--set", f'network.connect=["{endpoint}"]', "--set", f'network.learner_listen=["{endpoint}"]'],
                              capture_output=True, text=True, timeout=60)
        assert best.returncode == 0, best.stdout + best.stderr
        assert out.stat().st_size > 1000
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
        lines.append(rest)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "all services stopped" in "".join(lines)
    assert (tmp_path / RUN / "checkpoint.safetensors").is_file()
