"""`forcegrasp up`: starts the local cluster, shows live progress, stops everything on Ctrl-C."""

import os
import re
import signal
import subprocess
import sys
import time

from forcegrasp.cli import SERVICES
from forcegrasp.transport import free_tcp_port


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie still answers kill 0; read its state.
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


def test_up_shows_progress_and_ctrl_c_stops_every_service(tmp_path):
    port = free_tcp_port()
    cmd = [
        sys.executable, "-m", "forcegrasp.cli", "up",
        "--set", "run.name=up", "--set", f"run.output_dir={tmp_path}", "--set", "env.object=camera",
        "--set", "actor.envs_per_actor=2", "--set", "actor.random_steps=100", "--set", "actor.publish_batch=16",
        "--set", f'network.learner_listen=["tcp/127.0.0.1:{port}"]', "--set", "learner.stats_every_s=0.5",
        "--set", "learner.sac.learning_starts=200", "--set", "learner.sac.hidden=[32, 32]",
        "--set", "learner.sac.batch_size=32",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines, pids = [], []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("started"):
                pids = [int(p) for p in re.findall(r"pid (\d+)", line)]
            if re.search(r"env steps, \d+/s \| .*[1-9][\d.]*k? updates \| online success", line):
                break
        assert len(pids) == 3 + ("evaluator" in SERVICES), "".join(lines)  # learner, two actors, evaluator
        assert any(re.search(r" updates \| online success", l) for l in lines), "".join(lines)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
        lines.append(out)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for pid in pids:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
    text = "".join(lines)
    assert proc.returncode == 0, text
    assert "all services stopped" in text
    assert re.search(r"up: [\d,]+ env steps in [\d.]+ min of this start", text), text  # the exit summary
    assert not [pid for pid in pids if _alive(pid)]
    assert (tmp_path / "up" / "checkpoint.safetensors").is_file()  # the learner checkpointed on SIGINT
    assert (tmp_path / "up" / "logs" / "learner.log").is_file()
