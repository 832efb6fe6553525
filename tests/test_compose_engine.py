"""``docker compose up``, for real: the project's Dockerfile and compose.yaml on a Docker engine.

What a user does, in order, against one compose project: build the one image, ``up`` (learner, one
actor, evaluator), see training progress in the learner's log and the evaluator score a checkpoint,
``GET /best`` and ``forcegrasp best --out`` from the host (over HTTP and over Zenoh through the
published learner port), ``--scale actor=3``, an actor on a "spare machine" (a container on a
network of its own that reaches the learner only through the published port, as docs/docker.md
tells a user), ``stop`` (the learner writes its checkpoint), ``up`` again (the step counter goes
on from the checkpoint), ``down -v`` (the volume is gone).

It needs a Docker engine and a compose client, so it is marked ``docker`` and deselected by
default (pyproject's addopts). Run it here with:

    bash ../shared/docker/engine.sh
    python -m pytest -m docker tests/test_compose_engine.py -s

Without an engine it fails and says so: it is only ever run on purpose. The timings it prints
are summarised in docs/docker.md.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest

from forcegrasp.config import ENV_PREFIX

pytestmark = [pytest.mark.docker, pytest.mark.slow]

REPO = Path(__file__).resolve().parent.parent
FAST = REPO / "tests" / "data" / "compose.fast.yaml"   # short checkpoint/eval intervals, 2 envs per actor
RUN = "ctest"
INGESTED = re.compile(r"ingested (\d+) .* actors (\d+) sending: ?(.*)$")


def compose_client() -> list[str]:
    docker = shutil.which("docker")
    if docker and subprocess.run([docker, "compose", "version"], capture_output=True).returncode == 0:
        return [docker, "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    pytest.fail("no docker compose client: start the engine first (bash ../shared/docker/engine.sh)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def sh(args: list[str], timeout: float = 300, check: bool = True, env=None) -> subprocess.CompletedProcess:
    proc = subprocess.run(args, capture_output=True, text=True, timeout=timeout, cwd=REPO, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(args)} exited {proc.returncode}:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


class Project:
    """One compose project (its own name, ports and volume) and the timings of what it did."""

    def __init__(self, address: str):
        self.name = f"fgtest{os.getpid()}"
        self.address = address
        self.learner_port, self.http_port = free_port(), free_port()
        self.client = compose_client()
        self.env = {k: v for k, v in os.environ.items() if not k.startswith(ENV_PREFIX)}
        self.env.update(FORCEGRASP_RUN_NAME=RUN, FORCEGRASP_ENV_OBJECT="camera", PUBLISH_ADDRESS=address,
                        LEARNER_PORT=str(self.learner_port), HTTP_PORT=str(self.http_port))
        self.t0 = time.monotonic()
        self.times: dict[str, float] = {}

    def mark(self, what: str) -> None:
        self.times[what] = round(time.monotonic() - self.t0, 1)
        print(f"[compose test] {self.times[what]:7.1f} s  {what}", flush=True)

    def compose(self, *args: str, timeout: float = 300, check: bool = True) -> subprocess.CompletedProcess:
        return sh(self.client + ["-p", self.name, "-f", "compose.yaml", "-f", str(FAST), *args],
                  timeout=timeout, check=check, env=self.env)

    def learner_lines(self) -> list[str]:
        return self.compose("logs", "--no-color", "learner").stdout.splitlines()

    def learner_state(self) -> tuple[int, int, list[str]]:
        """(transitions ingested, actors sending, their ids) from the learner's latest stats line."""
        for line in reversed(self.learner_lines()):
            m = INGESTED.search(line)
            if m:
                return int(m.group(1)), int(m.group(2)), m.group(3).split()
        return 0, 0, []

    def wait(self, what: str, condition, timeout: float):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = condition()
            if value:
                self.mark(what)
                return value
            time.sleep(3)
        logs = self.compose("logs", "--no-color", "--tail", "40", check=False).stdout
        raise AssertionError(f"timed out after {timeout:.0f} s waiting for: {what}\n{logs[-6000:]}")

    def http(self, path: str):
        url = f"http://{self.address}:{self.http_port}{path}"
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                return r.status, r.read()
        except urllib.error.HTTPError as e:
            return e.code, e.read()
        except OSError:
            return None, b""


def best_scored(p: Project):
    status, body = p.http("/best")
    return json.loads(body) if status == 200 else None


def test_compose_up_trains_serves_scales_and_resumes(tmp_path):
    spare_net = f"fgspare{os.getpid()}"
    sh(["docker", "info"], timeout=30)
    # The spare machine's network, created first: its gateway is the address at which that
    # "machine" sees this host, so the cluster publishes its ports there.
    sh(["docker", "network", "create", spare_net])
    gateway = sh(["docker", "network", "inspect", spare_net, "-f", "{{(index .IPAM.Config 0).Gateway}}"]).stdout.strip()
    p = Project(gateway)
    spare = f"{p.name}-spare"
    try:
        p.compose("build", timeout=900)
        p.mark("image built")
        images = {img for img in sh(["docker", "images", "--format", "{{.Repository}}:{{.Tag}}"]).stdout.split()
                  if img.startswith(p.name)}
        assert not images, f"compose built per-service images {images}: all three must share forcegrasp:latest"
        size = sh(["docker", "image", "inspect", "forcegrasp:latest", "-f", "{{.Size}}"]).stdout.strip()
        print(f"[compose test] image forcegrasp:latest: {int(size) / 1e9:.2f} GB", flush=True)
        torch_line = sh(["docker", "run", "--rm", "--entrypoint", "python", "forcegrasp:latest",
                         "scripts/check_torch.py", "cpu"]).stdout.strip()
        assert torch_line.startswith("ok: torch") and "CPU-only" in torch_line, torch_line

        p.compose("up", "-d")
        p.mark("up")
        first = p.wait("learner ingesting from 1 actor", lambda: (lambda s: s if s[0] > 0 and s[1] == 1 else None)(
            p.learner_state()), timeout=240)
        p.wait("learner step count rising", lambda: p.learner_state()[0] > first[0], timeout=120)
        best = p.wait("evaluator scored a checkpoint (GET /best)", lambda: best_scored(p), timeout=300)
        assert best["run"] == RUN and best["step"] > 0, best

        out = tmp_path / "best-http.safetensors"
        sh(["forcegrasp", "best", "--url", f"http://{gateway}:{p.http_port}", "--out", str(out)], timeout=60)
        out_z = tmp_path / "best-zenoh.safetensors"
        sh(["forcegrasp", "best", "--out", str(out_z), "--timeout", "20", "--set", f"run.name={RUN}",
            "--set", f'network.connect=["tcp/{gateway}:{p.learner_port}"]'], timeout=90)
        from forcegrasp.policy import Policy
        for f in (out, out_z):
            policy = Policy.load(f)  # the full policy-file parse
            assert policy.metadata.object_name == "camera" and policy.metadata.obs_dim == 77
        p.mark("forcegrasp best from the host (HTTP and Zenoh)")

        p.compose("up", "-d", "--no-recreate", "--scale", "actor=3")
        p.wait("learner counts 3 actors", lambda: p.learner_state()[1] == 3, timeout=240)

        # An actor on a spare machine: its own network, the learner reached at the published port.
        sh(["docker", "run", "-d", "--rm", "--init", "--name", spare, "--network", spare_net, "forcegrasp:latest",
            "actor", "--id", "spare-1", "--seed", "90001", "--set", f'network.connect=["tcp/{gateway}:{p.learner_port}"]',
            "--set", f"run.name={RUN}", "--set", "env.object=camera", "--set", "actor.envs_per_actor=2"])
        p.wait("the spare machine's actor is ingested", lambda: "spare-1" in p.learner_state()[2], timeout=240)
        sh(["docker", "stop", spare], timeout=60, check=False)

        p.compose("stop", timeout=180)
        p.mark("stopped")
        stopped = [line for line in p.learner_lines() if "stopped at" in line]
        assert stopped, "the learner did not log its final checkpoint"
        n_stop = int(re.search(r"stopped at (\d+) transitions, checkpoint written", stopped[-1]).group(1))
        assert n_stop > 0

        p.compose("up", "-d", "--scale", "actor=1")
        resumed = p.wait("learner resumed from its checkpoint", lambda: [
            line for line in p.learner_lines() if "resumed from" in line], timeout=180)
        n_resumed = int(re.search(r"resumed from \S+: (\d+) transitions ingested", resumed[-1]).group(1))
        assert n_resumed == n_stop, (n_resumed, n_stop)
        p.wait("step counter continues past the checkpoint", lambda: p.learner_state()[0] > n_stop, timeout=180)
    finally:
        sh(["docker", "rm", "-f", spare], check=False)
        p.compose("down", "-v", "--remove-orphans", timeout=180, check=False)
        sh(["docker", "network", "rm", spare_net], check=False)
    volumes = sh(["docker", "volume", "ls", "-q"]).stdout.split()
    assert not [v for v in volumes if v.startswith(p.name)], "down -v left the runs volume behind"
    p.mark("down -v")
    print("[compose test] timings " + json.dumps(p.times), flush=True)
