"""``forcegrasp up``: the whole cluster as local processes on loopback, with live progress.

Starts the learner, ``actor.num_actors`` actors and the evaluator from one
resolved configuration file, prints one progress line every few seconds from the services' own
stats messages (a status line, rewritten in place on a terminal), restarts a service that dies (with backoff; it gives up on one that keeps crashing,
`forcegrasp.supervisor`), and on Ctrl-C (or SIGTERM, or when its output pipe closes) stops them all:
SIGINT first so the learner writes its checkpoint, SIGKILL after a grace period.
"""

from __future__ import annotations

import argparse
import functools
import os
import signal
import sys
import time
from pathlib import Path

from forcegrasp.config import add_config_arguments, config_from_args
from forcegrasp.console import StatusPrinter, exit_summary, resume_notice, status_line
from forcegrasp.protocol import Keys, ProtocolError, decode_stats
from forcegrasp.rundir import RunDir
from forcegrasp.runtime import open_service_session
from forcegrasp.supervisor import GRACE_S, RestartPolicy, Supervisor
from forcegrasp.transport import QueueSubscriber, close_session


def service_commands(config_path: Path, num_actors: int, evaluator: bool = True, seed: int = 0) -> dict[str, list[str]]:
    py = [sys.executable, "-m"]
    commands = {"learner": py + ["forcegrasp_learner", "--config", str(config_path)]}
    for i in range(num_actors):
        commands[f"actor-{i}"] = py + ["forcegrasp_actor", "--config", str(config_path), "--id", f"actor-{i}",
                                       "--seed", str(seed + 1000 * (i + 1))]
    if evaluator:
        commands["evaluator"] = py + ["forcegrasp_evaluator", "--config", str(config_path)]
    return commands


def evaluator_summary(ev: dict) -> str:
    """The evaluator's figures from its stats: the latest checkpoint's and the best's held-out success."""
    latest = ("-" if ev.get("latest_success_rate") is None else
              f"{ev['latest_success_rate']:.0%} of {ev.get('latest_episodes')} (step {ev.get('latest_step')})")
    best = ("-" if ev.get("best_success_rate") is None else
            f"{ev['best_success_rate']:.0%} of {ev.get('best_episodes')} (step {ev['best_step']})")
    return f"evaluator: latest held-out {latest}, best held-out {best}"


def drop_closed_output() -> None:
    """Point a closed stdout or stderr at /dev/null, so that later writes and the interpreter's
    flush at exit do not fail again."""
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except BrokenPipeError:
                os.dup2(null, stream.fileno())
            except (OSError, ValueError):
                pass
    finally:
        os.close(null)


def up(config, config_path: Path, stop_after: float | None = None, log=print, evaluator: bool = True,
       policy: RestartPolicy = RestartPolicy(), tty: bool = False) -> int:
    """Runs the cluster; the exit status is 0 after ``stop_after`` seconds or a signal, 1 when the
    output pipe closed or a service kept crashing. ``tty``: ``log`` is a terminal's print (the status
    line is rewritten in place); otherwise a plain status line every 10 s."""
    files = RunDir.of(config)
    resumed = resume_notice(files)
    files.root.mkdir(parents=True, exist_ok=True)
    config_path.write_text(config.to_toml())
    logs = files.logs
    logs.mkdir(exist_ok=True)
    state = {"stop": False, "status": 0}

    printer = StatusPrinter(log, tty)

    def guarded(write, message: str) -> None:  # `forcegrasp up | head`: the services must still be stopped
        try:
            write(message)
        except BrokenPipeError:
            state.update(stop=True, status=1)
            drop_closed_output()

    def say(message: str) -> None:
        guarded(printer.say, message)

    def on_signal(signum, frame):
        state["stop"] = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    commands = service_commands(config_path, config.actor.num_actors, evaluator, config.run.seed)
    services = Supervisor(commands, logs, policy, say)
    session = stats_sub = None
    latest: dict[str, dict] = {}
    t0 = time.monotonic()
    if resumed:
        say(resumed)
    try:
        for name in commands:
            services.start(name)
            if name == "learner":
                time.sleep(0.5)  # actors connect faster when the learner already listens
        say(f"started {', '.join(f'{n} (pid {p.pid})' for n, p in services.procs.items())}; logs in {logs}; "
            "Ctrl-C stops")
        session = open_service_session(config, "monitor")
        stats_sub = QueueSubscriber(session, Keys(config.run.name).all_stats, maxsize=256, put_timeout=0.0)
        last_line = time.monotonic()
        while not state["stop"] and (stop_after is None or time.monotonic() - t0 < stop_after):
            payload = stats_sub.get(timeout=0.2)
            if payload is not None:
                try:
                    s = decode_stats(payload)
                    latest[s.service if s.service in ("learner", "evaluator") else s.id] = s.values
                except ProtocolError:
                    pass
            failure = services.check()
            if failure is not None:
                say(failure)
                state["status"] = 1
                break
            if time.monotonic() - last_line > 2.0:
                guarded(printer.status, status_line(latest, time.monotonic() - t0))
                last_line = time.monotonic()
    finally:
        if stats_sub is not None:
            stats_sub.close()
        close_session(session)
        say("stopping: SIGINT to every service, the learner writes its checkpoint")
        services.stop(GRACE_S)
    say("all services stopped")
    for line in exit_summary(files, latest, time.monotonic() - t0, config.run.name):
        say(line)
    return state["status"]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp up", description=__doc__.splitlines()[0])
    add_config_arguments(parser)
    parser.add_argument("--stop-after", type=float, default=None, help="stop the cluster after this many seconds")
    parser.add_argument("--no-evaluator", action="store_true",
                        help="leave the evaluator out (run it on another machine, or measure training alone)")
    args = parser.parse_args(argv)
    config = config_from_args(args)
    path = RunDir.of(config).cluster_config
    log = functools.partial(print, flush=True)  # lines reach a pipe at once; a closed one shows at once
    return up(config, path, args.stop_after, log=log, evaluator=not args.no_evaluator, tty=sys.stdout.isatty())
