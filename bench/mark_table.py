"""Per-mark tables of `forcegrasp experiment` records, as docs/recipe.md prints them: for each run,
the held-out success of the evaluator's pick, of the latest snapshot and online (last 100
episodes) at every mark, with the environment steps trained so far; then one line per run with
the minutes to 50 / 80 / 90 % (the first mark whose pick reached it), the final pick, the env steps
the first pick at or above 90 % was trained on, and the run's env steps per second.

Writing these tables by hand from the JSON is where figures got mistyped; this prints them. Only
version-2 records are read (`forcegrasp.cli.experiment.check_record`).

    python bench/mark_table.py experiments/n-def60-camera-s1.json experiments/n-paper60-camera-s1.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ablation_table import steps_per_s, steps_to

from forcegrasp.cli.experiment import RecordError, read_record
from forcegrasp.cli.experiment_plot import object_set

RATES = (0.5, 0.8, 0.9)


def _pct(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.0f} %"


def _test(mark: dict, which: str) -> float | None:
    result = mark.get("test", {}).get(which)
    return None if result is None else result["success_rate"]


def minutes_to(record: dict, rate: float) -> float | None:
    """Minute of the first mark whose pick scored >= rate on the held-out placements (None: never)."""
    for mark in sorted(record.get("marks", []), key=lambda m: m["minute"]):
        value = _test(mark, "best")
        if value is not None and value >= rate:
            return mark["minute"]
    return None


def run_name(record: dict) -> str:
    return f"{record.get('label') or '?'}, {object_set(record)}, seed {record['seed']}" + (
        "" if record.get("force_feedback", True) else ", no force feedback")


def marks_table(records: list[dict]) -> str:
    """One markdown table: four rows per run (pick, latest, online, env steps), a column per mark;
    a run of several objects adds its pick's figure on each object (the pick's row is their min)."""
    minutes = sorted({m["minute"] for r in records for m in r.get("marks", [])})
    lines = ["| run | minute | " + " | ".join(f"{m:g}" for m in minutes) + " |",
             "|---|---|" + "---:|" * len(minutes)]
    for record in records:
        by_minute = {m["minute"]: m for m in record.get("marks", [])}

        def row(title: str, value) -> str:
            return f"| {title} | " + " | ".join(
                "" if (m := by_minute.get(minute)) is None else value(m) for minute in minutes) + " |"

        lines.append(row(f"{run_name(record)} | pick ({record.get('episodes', '?')} placements)",
                         lambda m: _pct(_test(m, "best"))))
        several = record.get("objects") or []
        for obj in several if len(several) > 1 else []:
            lines.append(row(f"| pick on {obj}", lambda m, o=obj: _pct(
                (m.get("test", {}).get("best", {}).get("objects", {}).get(o) or {}).get("success_rate"))))
        lines.append(row("| latest snapshot", lambda m: _pct(_test(m, "latest"))))
        lines.append(row("| online (last 100 episodes)",
                         lambda m: _pct((m.get("online") or {}).get("success_rate"))))
        lines.append(row("| env steps (latest)",
                         lambda m: "–" if "latest" not in m.get("steps", {}) else f"{m['steps']['latest'] / 1000:.0f} k"))
    return "\n".join(lines)


def summary_table(records: list[dict]) -> str:
    """One line per run: minutes to 50 / 80 / 90 %, final pick, pick's steps at 90 %, env steps/s."""
    lines = ["| run | " + " | ".join(f"to {100 * r:.0f} %" for r in RATES)
             + " | final pick | to 90 %: pick's env steps | env steps/s |",
             "|---|" + "---:|" * (len(RATES) + 3)]
    for record in records:
        last = max(record.get("marks", []), key=lambda m: m["minute"], default=None)
        to = ["–" if (m := minutes_to(record, r)) is None else f"{m:g} min" for r in RATES]
        steps, speed = steps_to(record), steps_per_s(record)
        lines.append(f"| {run_name(record)} | " + " | ".join(to)
                     + f" | {_pct(None if last is None else _test(last, 'best'))}"
                     + f" | {'–' if steps is None else f'{steps / 1000:.0f} k'}"
                     + f" | {'?' if speed is None else f'{speed:.0f}'} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("records", nargs="+", type=Path)
    try:
        records = [read_record(p) for p in parser.parse_args(argv).records]
    except (RecordError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(marks_table(records) + "\n\n" + summary_table(records))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
