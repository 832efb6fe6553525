"""bench/mark_table.py: minutes to a rate come from the first mark whose pick reached it, a mark a
run never took stays empty, the per-mark rows print the record's own figures, and a file that is not
a version-2 experiment record is refused, naming it."""

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))  # mark_table reuses ablation_table's step helpers
spec = importlib.util.spec_from_file_location("mark_table", ROOT / "bench" / "mark_table.py")
mark_table = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mark_table)


def record(label, marks, seed=1):
    """marks: (minute, pick, latest, online) success rates; steps grow 20 k a mark."""
    return {"format": "forcegrasp-experiment", "version": 2,
            "label": label, "seed": seed, "object": "camera", "force_feedback": True, "episodes": 100,
            "marks": [{"minute": m, "elapsed_s": 60 * m, "steps": {"latest": 20_000 * i, "best": 15_000 * i},
                       "test": {"best": {"success_rate": b}, "latest": {"success_rate": lt}},
                       "online": {"success_rate": o}} for i, (m, b, lt, o) in enumerate(marks, 1)]}


def test_minutes_to_is_the_first_mark_at_or_above_the_rate():
    r = record("x", [(5, 0.3, 0.2, 0.1), (10, 0.85, 0.9, 0.5), (15, 0.7, 0.6, 0.9), (20, 0.95, 0.1, 0.2)])
    assert mark_table.minutes_to(r, 0.5) == 10
    assert mark_table.minutes_to(r, 0.8) == 10
    assert mark_table.minutes_to(r, 0.9) == 20  # the latest snapshot's 90 % at 10 does not count
    assert mark_table.minutes_to(r, 0.99) is None


def test_tables_print_each_runs_own_marks_and_leave_missing_ones_empty():
    short = record("short", [(5, 0.0, 0.0, 0.0), (10, 0.91, 0.5, 0.4)])
    long = record("long", [(5, 0.12, 0.1, 0.03), (10, 0.6, 0.54, 0.65), (15, 1.0, 0.96, 1.0)], seed=2)
    marks = mark_table.marks_table([short, long]).splitlines()
    assert marks[0] == "| run | minute | 5 | 10 | 15 |"
    assert marks[2] == "| short, camera, seed 1 | pick (100 placements) | 0 % | 91 % |  |"
    assert marks[5] == "| | env steps (latest) | 20 k | 40 k |  |"
    assert marks[7] == "| | latest snapshot | 10 % | 54 % | 96 % |"
    assert marks[8] == "| | online (last 100 episodes) | 3 % | 65 % | 100 % |"
    summary = mark_table.summary_table([short, long]).splitlines()
    # short: 90 % at minute 10 from a pick of 30 k steps; 40 k steps in 600 s
    assert summary[2] == "| short, camera, seed 1 | 10 min | 10 min | 10 min | 91 % | 30 k | 67 |"
    assert summary[3] == "| long, camera, seed 2 | 10 min | 15 min | 15 min | 100 % | 45 k | 67 |"


def test_records_are_read_only_at_version_2(tmp_path, capsys):
    good, old = tmp_path / "good.json", tmp_path / "old.json"
    good.write_text(json.dumps(record("x", [(5, 0.3, 0.2, 0.1)])))
    assert mark_table.main([str(good)]) == 0
    assert "| x, camera, seed 1 |" in capsys.readouterr().out
    old.write_text(json.dumps({k: v for k, v in record("x", [(5, 0.3, 0.2, 0.1)]).items() if k not in ("format", "version")}))
    assert mark_table.main([str(good), str(old)]) == 2
    out = capsys.readouterr()
    assert out.out == "" and "old.json: not a versioned experiment record" in out.err and "version 2" in out.err


def test_a_run_of_several_objects_is_named_for_its_set_with_a_row_per_object():
    r = record("generalist", [(20, 0.4, 0.1, 0.5), (40, 0.8, 0.7, 0.8)])
    r.update(objects=["mug", "camera"], object="mug")
    for i, (mug, camera) in enumerate([(0.4, 0.9), (0.8, 1.0)]):
        r["marks"][i]["test"]["best"]["objects"] = {"mug": {"success_rate": mug}, "camera": {"success_rate": camera}}
    marks = mark_table.marks_table([r]).splitlines()
    assert marks[2] == "| generalist, mug+camera, seed 1 | pick (100 placements) | 40 % | 80 % |"
    assert marks[3:5] == ["| | pick on mug | 40 % | 80 % |", "| | pick on camera | 90 % | 100 % |"]
    assert marks[5] == "| | latest snapshot | 10 % | 70 % |"
