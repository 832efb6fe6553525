"""Child processes kept running, within limits, and never outliving their supervisor.

`forcegrasp up` runs its services through `Supervisor`. A service that dies is started again after
a delay that doubles with each crash, so one that fails at start cannot spin; once it has crashed
`RestartPolicy.max_crashes` times within `window_s` the supervisor gives up with one message naming
it, its exit code and its log's last lines, and the caller stops the rest. Each service's log is
opened once, for appending, and closed by `stop`. On Linux each child asks the kernel for SIGTERM
when its supervisor dies (PR_SET_PDEATHSIG), so even a SIGKILL of the supervisor leaves no orphan.
"""

from __future__ import annotations

import collections
import ctypes
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

GRACE_S = 20.0
PR_SET_PDEATHSIG = 1  # linux/prctl.h


@dataclass(frozen=True)
class RestartPolicy:
    first_delay_s: float = 1.0  # doubled after each crash ...
    max_delay_s: float = 30.0  # ... up to this
    max_crashes: int = 5  # this many crashes ...
    window_s: float = 60.0  # ... within this long: give up
    stable_s: float = 60.0  # a run this long wipes the service's crash record


class Restarts:
    """One service's crash record under a `RestartPolicy`."""

    def __init__(self, policy: RestartPolicy):
        self.policy = policy
        self.crashes: collections.deque[float] = collections.deque()
        self.streak = 0

    def crashed(self, now: float, ran_s: float) -> float | None:
        """The delay before the next start, or None to give up."""
        p = self.policy
        if ran_s >= p.stable_s:
            self.crashes.clear()
            self.streak = 0
        self.streak += 1
        self.crashes.append(now)
        while now - self.crashes[0] > p.window_s:
            self.crashes.popleft()
        if len(self.crashes) >= p.max_crashes:
            return None
        return min(p.max_delay_s, p.first_delay_s * 2 ** (self.streak - 1))


def _prctl():
    """libc's prctl, looked up here: a forked child of a threaded parent should do no more than call it."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    return prctl


_PRCTL = _prctl()


def parent_death_signal(sig: int = signal.SIGTERM):
    """A ``preexec_fn`` that has the kernel send ``sig`` to the child when the thread that forked it
    exits (so call Popen from a thread that lives as long as the children should); None off Linux."""
    if _PRCTL is None:
        return None
    parent, sig = os.getpid(), int(sig)

    def preexec() -> None:
        _PRCTL(PR_SET_PDEATHSIG, sig, 0, 0, 0)
        if os.getppid() != parent:  # the parent died before prctl took effect: no signal would come
            os._exit(1)

    return preexec


def exit_text(returncode: int) -> str:
    if returncode < 0:
        try:
            return f"was killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"was killed by signal {-returncode}"
    return f"exited with code {returncode}"


def last_lines(path: Path, n: int = 15, max_bytes: int = 8192) -> list[str]:
    try:
        with open(path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - max_bytes))
            return f.read().decode(errors="replace").splitlines()[-n:]
    except OSError:
        return []


def stop_all(procs: dict[str, subprocess.Popen], log=print, grace_s: float = GRACE_S) -> None:
    """SIGINT to every live service, then SIGKILL whatever has not exited after ``grace_s``."""
    for p in procs.values():
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    deadline = time.monotonic() + grace_s
    for name, p in procs.items():
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log(f"{name} did not stop in {grace_s:.0f} s: SIGKILL")
            p.kill()
            p.wait()


class Supervisor:
    """Named commands as child processes, each in a session of its own (a terminal's Ctrl-C reaches
    the supervisor alone, which stops them in order), output appended to ``log_dir/<name>.log``.
    `start` and `check` belong to one long-lived thread: the children's death signal is tied to it."""

    def __init__(self, commands: dict[str, list[str]], log_dir: Path, policy: RestartPolicy = RestartPolicy(),
                 log=print):
        self.commands = dict(commands)
        self.log_dir = Path(log_dir)
        self.policy = policy
        self.log = log
        self.procs: dict[str, subprocess.Popen] = {}
        self._files: dict[str, IO[bytes]] = {}
        self._started: dict[str, float] = {}
        self._due: dict[str, float] = {}  # dead services: when they start again
        self._restarts = {name: Restarts(policy) for name in self.commands}

    def log_path(self, name: str) -> Path:
        return self.log_dir / f"{name}.log"

    def start(self, name: str) -> subprocess.Popen:
        if name not in self._files:
            self._files[name] = open(self.log_path(name), "ab")
        self.procs[name] = subprocess.Popen(self.commands[name], stdout=self._files[name], stderr=subprocess.STDOUT,
                                            start_new_session=True, preexec_fn=parent_death_signal())
        self._started[name] = time.monotonic()
        return self.procs[name]

    def check(self) -> str | None:
        """Note the services that died and start those whose delay is over. Returns the message to
        give up with when one has crashed too often, else None."""
        now = time.monotonic()
        for name, p in self.procs.items():
            if name in self._due or p.poll() is None:
                continue
            delay = self._restarts[name].crashed(now, now - self._started[name])
            if delay is None:
                return self._give_up(name, p.returncode)
            self.log(f"{name} {exit_text(p.returncode)}; restarting it in {delay:g} s (see {self.log_path(name)})")
            self._due[name] = now + delay
        for name, at in list(self._due.items()):
            if now >= at:
                del self._due[name]
                self.start(name)
        return None

    def _give_up(self, name: str, returncode: int) -> str:
        crashes = self._restarts[name].crashes
        tail = "".join(f"\n    {line}" for line in last_lines(self.log_path(name))) or " (empty)"
        return (f"{name} {exit_text(returncode)} and has crashed {len(crashes)} times in "
                f"{crashes[-1] - crashes[0]:.0f} s: giving up on it. Last lines of {self.log_path(name)}:{tail}")

    def stop(self, grace_s: float = GRACE_S) -> None:
        """Stop every service (`stop_all`) and close the logs; pending restarts are dropped."""
        self._due.clear()
        try:
            stop_all(self.procs, self.log, grace_s)
        finally:
            for f in self._files.values():
                f.close()
            self._files.clear()
