"""What `forcegrasp up` says on the console: a status line that fits a terminal, the resume notice
and the exit summary. Pure functions of the services' stats and the run's files, so they are tested
without a cluster.

On a terminal the status line is rewritten in place; in a log (a pipe, a file) it is a plain line
every few seconds. Every figure carries its name: the actors' online success is on sampled actions
while the weights change under them, the evaluator's is deterministic on held-out placements.
"""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path

from forcegrasp.rundir import RunDir

WIDTH = 100


def _k(n: float) -> str:
    """1234 -> '1.2k', 1234567 -> '1.23M': counts short enough for one line."""
    n = float(n)
    if n >= 1e6:
        return f"{n / 1e6:.2f}M"
    if n >= 1e4:
        return f"{n / 1e3:.0f}k"
    if n >= 1e3:
        return f"{n / 1e3:.1f}k"
    return f"{n:.0f}"


def status_line(stats: dict, elapsed_s: float, width: int = WIDTH) -> str:
    """One line, at most ``width`` characters, from the latest stats of each service; the optional
    figures (update count, actor count) go first when the line would be too long."""
    learner = stats.get("learner")
    if learner is None:
        return f"{elapsed_s / 60:.1f} min | waiting for the learner..."[:width]
    actors = [v for k, v in stats.items() if k not in ("learner", "evaluator")]
    rate = sum(a.get("steps_per_s", 0.0) for a in actors)
    online = learner.get("success_rate")
    ev = stats.get("evaluator") or {}
    best = ("-" if ev.get("best_success_rate") is None else
            f"{ev['best_success_rate']:.0%} (step {_k(ev['best_step'])})")
    parts = {"time": f"{elapsed_s / 60:.1f} min", "steps": f"{_k(learner['ingested'])} env steps, {rate:.0f}/s",
             "actors": f"{len(actors)} actors", "updates": f"{_k(learner['updates'])} updates",
             "online": "online success " + ("-" if online is None else f"{online:.0%}") + _worst(learner),
             "best": f"best held-out {best}"}
    levels = [a["curriculum_level"] for a in actors if "curriculum_level" in a]
    if levels:  # the randomisation curriculum (forcegrasp.curriculum): how much of the ranges is open
        parts["ranges"] = f"ranges {sum(levels) / len(levels):.0%} open"
    for optional in ("actors", "updates", "ranges"):
        if len(" | ".join(parts.values())) <= width:
            break
        parts.pop(optional, None)
    return " | ".join(parts.values())[:width]


def _worst(learner: dict) -> str:
    """`` (worst NAME 40%)`` when the learner reports several objects' online success (env.objects)."""
    rates = {o: v["success_rate"] for o, v in (learner.get("objects") or {}).items() if v.get("success_rate") is not None}
    if not rates:
        return ""
    name = min(rates, key=rates.get)
    return f" (worst {name} {rates[name]:.0%})"


def read_checkpoint_step(path: Path) -> int | None:
    """The transitions a learner checkpoint had ingested (its header), or None without one. Reads
    the safetensors header only: no tensors, no torch."""
    try:
        with open(path, "rb") as f:
            (size,) = struct.unpack("<Q", f.read(8))
            header = json.loads(f.read(size))
        sac = json.loads(header["__metadata__"]["forcegrasp.sac"])
        return int(sac["extra"]["ingested"])
    except (OSError, struct.error, ValueError, KeyError, TypeError):
        return None


def resume_notice(files: RunDir) -> str | None:
    """'resumed from step N ...' when the run folder holds a learner checkpoint, else None."""
    step = read_checkpoint_step(files.checkpoint)
    if step is None:
        return None
    index = files.read_index() or {}
    kept = len(index.get("members", []))
    return (f"resumed run {files.root.name!r} from step {step:,} (its checkpoint); the evaluator keeps "
            f"{kept} checkpoint{'s' if kept != 1 else ''} from before")


def exit_summary(files: RunDir, stats: dict, elapsed_s: float, run_name: str) -> list[str]:
    """What a stopped run achieved: steps, wall-clock, the best policy, and how to fetch it."""
    learner = stats.get("learner") or {}
    steps = learner.get("ingested", read_checkpoint_step(files.checkpoint) or 0)
    lines = [f"{run_name}: {steps:,} env steps in {elapsed_s / 60:.1f} min of this start"]
    index = files.read_index() or {}
    best = next((m for m in index.get("members", []) if m.get("best")), None)
    if best is None:
        lines.append("no evaluated best policy yet")
        return lines
    lines.append(f"best policy: {files.top / best['file']} (step {best['step']:,}), "
                 f"{best['rank_success_rate']:.0%} of {best['rank_episodes']} held-out placements")
    lines.append(f"fetch it: forcegrasp best --set run.name={run_name} --out best.safetensors "
                 f"(or copy the file); test it: forcegrasp eval {files.top / best['file']}")
    return lines


class StatusPrinter:
    """Writes status lines: in place on a terminal, plain lines every ``every_s`` seconds otherwise."""

    def __init__(self, write, is_tty: bool, every_s: float = 10.0):
        self.write, self.is_tty, self.every_s = write, is_tty, every_s
        self._last = -1e9
        self._open = False

    def status(self, line: str) -> None:
        now = time.monotonic()
        if self.is_tty:
            self.write("\r" + line.ljust(WIDTH)[:WIDTH], end="")
            self._open = True
        elif now - self._last >= self.every_s:
            self.write(line)
            self._last = now

    def say(self, line: str) -> None:
        """A message of its own line (ends an in-place status line first)."""
        if self._open:
            self.write("")
            self._open = False
        self.write(line)
