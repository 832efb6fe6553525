"""bench/robustness_table.py: per-condition rows from the records tested under conditions, and a file
that is not a version-2 experiment record refused, naming it."""

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("robustness_table", ROOT / "bench" / "robustness_table.py")
robustness_table = importlib.util.module_from_spec(spec)
spec.loader.exec_module(robustness_table)
FIXTURES = sorted((ROOT / "tests" / "data" / "experiments").glob("*.json"))


def test_rows_come_from_the_records_tested_under_conditions(capsys):
    assert robustness_table.main([str(p) for p in FIXTURES]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| run | object | seed | randomisation | mark | 5x | noise_0.5 | mean | env steps | steps/s |"
    assert lines[2:] == ["| `fx-camera-s1` | camera | 1 | none (5× only) | 10 min | 60% | 60% | **60%** | 25 k | 50 |",
                         "| `fx-camera-s1` | camera | 1 | none (5× only) | 20 min | 100% | 100% | **100%** | 50 k | 50 |"]


def test_an_unversioned_record_is_refused(tmp_path, capsys):
    old = tmp_path / "old.json"
    old.write_text(json.dumps({k: v for k, v in json.loads(FIXTURES[0].read_text()).items() if k not in ("format", "version")}))
    assert robustness_table.main([str(FIXTURES[0]), str(old)]) == 2
    assert "old.json: not a versioned experiment record" in capsys.readouterr().err


def test_a_run_of_several_objects_is_left_to_the_mark_table(tmp_path, capsys):
    path = next(p for p in FIXTURES if json.loads(p.read_text()).get("conditions"))
    several = {**json.loads(path.read_text()), "objects": ["camera", "mug"], "label": "generalist"}
    (tmp_path / "g.json").write_text(json.dumps(several))
    assert robustness_table.main([str(path), str(tmp_path / "g.json")]) == 0
    with_it = capsys.readouterr().out
    assert robustness_table.main([str(path)]) == 0
    assert with_it == capsys.readouterr().out and with_it.count("fx-camera-s1") == 2
