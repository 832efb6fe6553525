"""bench/experiments_index.py: experiments/README.md indexes every kept record and is up to date."""

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))  # it reuses ablation_table's lever names
spec = importlib.util.spec_from_file_location("experiments_index", ROOT / "bench" / "experiments_index.py")
experiments_index = importlib.util.module_from_spec(spec)
spec.loader.exec_module(experiments_index)


def test_the_index_lists_every_record_and_is_up_to_date(capsys):
    assert experiments_index.main(["--check"]) == 0, capsys.readouterr().err
    text = (ROOT / "experiments" / "README.md").read_text()
    for path in (ROOT / "experiments").glob("*.json"):
        assert f"| {path.name} |" in text
    assert "| n-lndemo15-camera-s0.json | critic LayerNorm + 4 demonstrations per env | fast (fixed conditions) | yes | 0 | 15 " \
           "| camera-ff-5x-s0 |" in text
