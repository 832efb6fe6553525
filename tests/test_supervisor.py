"""`forcegrasp up`'s supervision, on real child processes: restarts back off and give up with a
message, no descriptor leaks, and no child outlives a supervisor killed with SIGKILL or one whose
output pipe closes. Every process is started here and ended here, by PID."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from forcegrasp.supervisor import Restarts, RestartPolicy, Supervisor
from forcegrasp.transport import free_tcp_port

LINUX = sys.platform.startswith("linux")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie still answers kill 0
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, IndexError):
        return False


def _gone_within(pids: list[int], seconds: float) -> list[int]:
    deadline = time.monotonic() + seconds
    while (alive := [p for p in pids if _alive(p)]) and time.monotonic() < deadline:
        time.sleep(0.05)
    return alive


def _kill(pids) -> None:
    for pid in pids:
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@pytest.mark.skipif(not LINUX, reason="counts /proc/self/fd")
def test_a_service_crashing_at_start_is_restarted_ever_later_then_given_up_on(tmp_path):
    crash = ["sh", "-c", 'echo "start $(date +%s.%N)"; echo "error: batch_size abc is not an int" >&2; exit 3']
    policy = RestartPolicy(first_delay_s=0.25, max_delay_s=10.0, max_crashes=5, window_s=30.0, stable_s=30.0)
    messages: list[str] = []
    before = _open_fds()
    services = Supervisor({"learner": crash}, tmp_path, policy, messages.append)
    try:
        services.start("learner")
        fds, failure = set(), None
        deadline = time.monotonic() + 15
        while failure is None and time.monotonic() < deadline:
            failure = services.check()
            fds.add(_open_fds())
            time.sleep(0.02)
    finally:
        services.stop(grace_s=2)
    starts = [float(line.split()[1]) for line in (tmp_path / "learner.log").read_text().splitlines()
              if line.startswith("start ")]
    gaps = [b - a for a, b in zip(starts, starts[1:])]
    assert failure is not None, messages
    assert len(starts) == 5 and len(messages) == 4, (starts, messages)  # one log, appended to
    assert all(b > a for a, b in zip(gaps, gaps[1:])), gaps
    assert all(gap >= 0.25 * 2**k - 0.02 for k, gap in enumerate(gaps)), gaps
    assert "learner" in failure and "exited with code 3" in failure, failure
    assert "error: batch_size abc is not an int" in failure, failure
    assert fds == {before + 1}, fds  # the log file, opened once
    assert _open_fds() == before  # ... and closed


def test_a_long_run_wipes_the_crash_record_and_crashes_spread_out_are_not_given_up_on():
    restarts = Restarts(RestartPolicy(first_delay_s=1, max_delay_s=4, max_crashes=3, window_s=60, stable_s=30))
    assert [restarts.crashed(t, 0.5) for t in (0, 2, 5)] == [1, 2, None]
    restarts = Restarts(RestartPolicy(first_delay_s=1, max_delay_s=4, max_crashes=3, window_s=60, stable_s=30))
    assert [restarts.crashed(t, 0.5) for t in (0, 2)] == [1, 2]
    assert restarts.crashed(40, 35) == 1  # it ran 35 s: healthy, back to the first delay
    assert [restarts.crashed(t, 0.5) for t in (42, 45)] == [2, None]
    restarts = Restarts(RestartPolicy(first_delay_s=1, max_delay_s=4, max_crashes=3, window_s=10, stable_s=30))
    assert [restarts.crashed(t, 5) for t in (0, 11, 22, 33)] == [1, 2, 4, 4]  # never 3 within 10 s


@pytest.mark.skipif(not LINUX, reason="PR_SET_PDEATHSIG is Linux's")
def test_no_child_outlives_a_supervisor_killed_with_sigkill(tmp_path):
    script = textwrap.dedent(f"""
        import sys, time
        from forcegrasp.supervisor import Supervisor
        services = Supervisor({{"sleeper": ["sleep", "60"],
                                "python": [sys.executable, "-c", "import time; time.sleep(60)"]}}, {str(tmp_path)!r})
        for name in services.commands:
            services.start(name)
        print(*(p.pid for p in services.procs.values()), flush=True)
        while True:
            services.check()
            time.sleep(0.1)
    """)
    supervisor = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    pids: list[int] = []
    try:
        pids = [int(p) for p in supervisor.stdout.readline().split()]
        assert len(pids) == 2 and all(_alive(p) for p in pids)
        supervisor.kill()
        supervisor.wait(timeout=10)
        assert not _gone_within(pids, 5.0)
    finally:
        supervisor.kill()
        supervisor.wait()
        supervisor.stdout.close()
        _kill(pids)


def test_up_stops_its_services_and_exits_when_its_output_pipe_closes(tmp_path):
    port = free_tcp_port()
    cmd = [sys.executable, "-m", "forcegrasp.cli", "up", "--no-evaluator",
           "--set", "run.name=pipe", "--set", f"run.output_dir={tmp_path}", "--set", "actor.num_actors=0",
           "--set", f'network.learner_listen=["tcp/127.0.0.1:{port}"]']
    errors = open(tmp_path / "stderr", "w+")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=errors, text=True)
    pids: list[int] = []
    try:
        line = proc.stdout.readline()
        pids = [int(p) for p in re.findall(r"pid (\d+)", line)]
        assert line.startswith("started") and pids, line
        proc.stdout.close()  # `forcegrasp up | head -1`: the next progress line meets a closed pipe
        assert proc.wait(timeout=25) == 1
        assert not _gone_within(pids, 1.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        _kill(pids)
        errors.close()
    assert "Error" not in (tmp_path / "stderr").read_text()  # it stopped them itself, no BrokenPipeError
