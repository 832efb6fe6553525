"""An actor on a "spare machine": learner and actor in separate network namespaces joined by a
veth pair, the actor pointed at the learner's address exactly as the README says. Then the
link is cut and restored: the actor buffers, never exits, and its batches arrive afterwards.

Needs root and iproute2 (CI and the development machines have both); skipped elsewhere.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
import uuid

import pytest

from forcegrasp.config import load_config
from forcegrasp.delivery import RESEND_AFTER_S

pytestmark = pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("ip") is None, reason="needs root and iproute2 for network namespaces"
)

SUBNET = "10.231.{}.{}"


def sh(*args: str) -> None:
    subprocess.run(args, check=True, capture_output=True, timeout=20)


@pytest.fixture
def two_hosts():
    tag = uuid.uuid4().hex[:6]
    hosts = {"learner": f"fgl{tag}", "actor": f"fga{tag}"}
    third = int(tag[:2], 16) % 200 + 20
    addr = {"learner": SUBNET.format(third, 1), "actor": SUBNET.format(third, 2)}
    veth = {"learner": f"vl{tag}", "actor": f"va{tag}"}
    try:
        for ns in hosts.values():
            sh("ip", "netns", "add", ns)
            sh("ip", "-n", ns, "link", "set", "lo", "up")
        sh("ip", "link", "add", veth["learner"], "type", "veth", "peer", "name", veth["actor"])
        for role in ("learner", "actor"):
            sh("ip", "link", "set", veth[role], "netns", hosts[role])
            sh("ip", "-n", hosts[role], "addr", "add", f"{addr[role]}/24", "dev", veth[role])
            sh("ip", "-n", hosts[role], "link", "set", veth[role], "up")
        yield hosts, addr, veth
    finally:
        for ns in hosts.values():
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=20)


def test_actor_on_another_host_joins_buffers_through_an_outage_and_catches_up(tmp_path, two_hosts):
    hosts, addr, veth = two_hosts
    port = 7447
    common = [
        "run.name=netns", f"run.output_dir={tmp_path}", "env.object=camera", "actor.envs_per_actor=2",
        "actor.random_steps=100", "actor.publish_batch=16", "learner.sac.learning_starts=200",
        "learner.sac.hidden=[32, 32]", "learner.sac.batch_size=32", "learner.stats_every_s=0.5",
        "network.lease_ms=1000",
    ]
    config = load_config(overrides=common + [f'network.learner_listen=["tcp/{addr["learner"]}:{port}"]'])
    (tmp_path / "learner.toml").write_text(config.to_toml())
    # The actor's side, as docs/docker.md tells a user on a spare machine: connect to the learner.
    actor_cmd = [sys.executable, "-m", "forcegrasp.cli", "actor", "--id", "remote", "--seed", "7",
                 "--set", f'network.connect=["tcp/{addr["learner"]}:{port}"]',
                 "--set", f'network.listen=["tcp/{addr["actor"]}:0"]'] + [a for c in common for a in ("--set", c)]
    learner = subprocess.Popen(
        ["ip", "netns", "exec", hosts["learner"], sys.executable, "-m", "forcegrasp_learner",
         "--config", str(tmp_path / "learner.toml")],
        stdout=open(tmp_path / "learner.log", "w"), stderr=subprocess.STDOUT,
    )
    actor = subprocess.Popen(["ip", "netns", "exec", hosts["actor"], *actor_cmd],
                             stdout=open(tmp_path / "actor.log", "w"), stderr=subprocess.STDOUT)

    def learner_ingested_from_remote() -> int:
        import re

        found = re.findall(r"ingested (\d+)", (tmp_path / "learner.log").read_text())
        return int(found[-1]) if found else 0

    def wait(what, predicate, timeout=90):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            assert learner.poll() is None, (tmp_path / "learner.log").read_text()[-2000:]
            assert actor.poll() is None, (tmp_path / "actor.log").read_text()[-2000:]
            value = predicate()
            if value:
                return value
            time.sleep(0.5)
        raise AssertionError(f"timed out: {what}\n{(tmp_path / 'learner.log').read_text()[-1500:]}\n"
                             f"{(tmp_path / 'actor.log').read_text()[-1500:]}")

    try:
        wait("transitions from the remote actor", lambda: learner_ingested_from_remote() >= 300)
        # Cut the wire: the actor keeps stepping into its bounded outbox and does not exit.
        sh("ip", "-n", hosts["actor"], "link", "set", veth["actor"], "down")
        time.sleep(4.0)
        before = learner_ingested_from_remote()
        assert actor.poll() is None
        sh("ip", "-n", hosts["actor"], "link", "set", veth["actor"], "up")
        wait("the actor reconnecting and delivering", lambda: learner_ingested_from_remote() > before + 300, timeout=120)
        # Nothing lost for good: batches the dead link swallowed leave holes until the actor resends
        # them (RESEND_AFTER_S), and the learner's gap count (open holes included) returns to 0.
        last_line = lambda: (tmp_path / "learner.log").read_text().strip().splitlines()[-1]  # noqa: E731
        wait("every hole refilled by the actor's resends", lambda: "gaps 0" in last_line(),
             timeout=10 + 3 * RESEND_AFTER_S)
    finally:
        for p in (actor, learner):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in (actor, learner):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
