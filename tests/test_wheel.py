"""The package outside the repository: a built wheel, installed into a fresh virtual environment
and run from another folder, finds its objects, labels and shipped policies (package data), and
its actor joins a learner started from the checkout over Zenoh on loopback.

The venv sees the already installed dependencies (``--system-site-packages``) so that the test
needs no network; the wheel's own ``forcegrasp`` shadows the checkout's, which the test checks.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from forcegrasp.config import load_config
from forcegrasp.protocol import Keys, decode_stats
from forcegrasp.transport import QueueSubscriber, close_session, free_tcp_port, open_session

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def venv(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                    str(tmp / "dist"), str(REPO)], check=True, capture_output=True, cwd=tmp)
    wheel = next((tmp / "dist").glob("forcegrasp-*.whl"))
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(tmp / "venv")], check=True)
    subprocess.run([str(tmp / "venv" / "bin" / "pip"), "install", "-q", "--no-deps", "--no-index", str(wheel)],
                   check=True, capture_output=True)
    elsewhere = tmp / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("FORCEGRASP_") and k != "PYTHONPATH"}
    return tmp / "venv", elsewhere, env


def run(venv, *args, timeout=300):
    bin_dir, cwd, env = venv[0] / "bin", venv[1], venv[2]
    return subprocess.run([str(bin_dir / args[0]), *args[1:]], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_gymnasium_make_steps_from_the_wheel(venv):
    code = ("import gymnasium, forcegrasp, numpy as np; "
            "print(forcegrasp.__file__); print(forcegrasp.ASSETS_DIR); "
            "env = gymnasium.make('FunctionalGrasp-Mug-v0'); obs, _ = env.reset(seed=0); "
            "obs, r, term, trunc, info = env.step(np.zeros(7, np.float32)); print(obs.shape, info['h'] > 0)")
    out = run(venv, "python", "-c", code)
    assert out.returncode == 0, out.stderr
    file, assets, result = out.stdout.strip().splitlines()
    assert file.startswith(str(venv[0])), f"imported {file}, not the wheel's copy"
    assert Path(assets).is_relative_to(venv[0]) and (Path(assets) / "objects" / "mug.json").is_file()
    assert result == "(77,) True"


def test_eval_runs_a_shipped_policy_from_the_wheel(venv):
    out = run(venv, "forcegrasp", "eval", "mug-ff-s0", "--episodes", "3")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "success" in out.stdout
    assert not any(venv[1].iterdir()) or all(p.name != "assets" for p in venv[1].iterdir())


def test_wheel_actor_joins_a_learner_from_the_checkout(venv, tmp_path):
    port = free_tcp_port()
    config = load_config(env={}, overrides=[
        "run.name=wheel", f"run.output_dir={tmp_path / 'runs'}", "env.object=camera", "actor.envs_per_actor=2",
        "actor.random_steps=100", "actor.publish_batch=16", "actor.demo_episodes=0",
        f'network.learner_listen=["tcp/127.0.0.1:{port}"]', "network.lease_ms=1000", "learner.stats_every_s=0.5",
        "learner.sac.learning_starts=200", "learner.sac.hidden=[32, 32]", "learner.sac.batch_size=32",
        "learner.sac.num_threads=1"])
    path = tmp_path / "cluster.toml"
    path.write_text(config.to_toml())
    procs = []
    session = open_session([], [f"tcp/127.0.0.1:{port}"])
    stats = QueueSubscriber(session, Keys("wheel").all_stats, maxsize=4096, put_timeout=0.0)
    try:
        with open(tmp_path / "learner.log", "wb") as log:
            procs.append(subprocess.Popen([sys.executable, "-m", "forcegrasp_learner", "--config", str(path)],
                                          stdout=log, stderr=subprocess.STDOUT, cwd=REPO))
        bin_dir, cwd, env = venv[0] / "bin", venv[1], venv[2]
        with open(tmp_path / "actor.log", "wb") as log:
            procs.append(subprocess.Popen([str(bin_dir / "forcegrasp"), "actor", "--config", str(path), "--id", "spare"],
                                          stdout=log, stderr=subprocess.STDOUT, cwd=cwd, env=env))
        ingested, deadline = 0, time.monotonic() + 120
        while ingested < 200 and time.monotonic() < deadline:
            for p in procs:
                assert p.poll() is None, (tmp_path / "learner.log").read_text()[-2000:] + \
                    (tmp_path / "actor.log").read_text()[-2000:]
            payload = stats.get(timeout=0.2)
            if payload is not None:
                s = decode_stats(payload)
                if s.service == "learner":
                    ingested = s.values["actors"].get("spare", {}).get("ingested", 0)
        assert ingested >= 200, (tmp_path / "actor.log").read_text()[-2000:]
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        stats.close()
        close_session(session)
