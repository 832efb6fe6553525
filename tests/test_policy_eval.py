"""`forcegrasp eval`: a policy file tested on held-out placements, one env setting swept."""

import json

import matplotlib.image
import numpy as np
import pytest

from forcegrasp.config import load_config
from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.evaluation import placements
from forcegrasp.cli.policy_eval import main
from forcegrasp.policy_file import actor_param_shapes, save_policy_file
from forcegrasp.runtime import policy_metadata


def constant_policy(path, object_name="camera", force_feedback=True, push=0.0):
    """A policy whose deterministic action is (push, 0, ..., 0) whatever it observes."""
    config = load_config(env={}, overrides=[f"env.object={object_name}", f"env.force_feedback={str(force_feedback).lower()}"])
    meta = policy_metadata(config, (8,), training_steps=1)
    weights = {k: np.zeros(s, np.float32) for k, s in actor_param_shapes(meta).items()}
    weights["layers.1.bias"][0] = np.arctanh(push)
    return save_policy_file(path, weights, meta)


def test_sweep_writes_rows_json_and_plot(tmp_path, capsys):
    policy = constant_policy(tmp_path / "p.safetensors", push=0.9)  # drives the hand along x: it fails
    out_json, out_png = tmp_path / "rows.json", tmp_path / "sweep.png"
    args = [str(policy), "--episodes", "3", "--sweep", "mass_scale=5,1", "--env", "object_tolerance=0.03",
            "--json", str(out_json), "--plot", str(out_png)]
    assert main(args) == 0
    rows = json.loads(out_json.read_text())["rows"]
    assert [r["value"] for r in rows] == [5.0, 1.0] and all(r["episodes"] == 3 for r in rows)
    assert [r["env"]["mass_scale"] for r in rows] == [5.0, 1.0]
    assert all(r["env"]["object_tolerance"] == 0.03 for r in rows)
    assert all(r["success_rate"] == 0.0 and sum(r["failures"].values()) == 3 for r in rows)
    assert "| mass_scale | success |" in capsys.readouterr().out
    assert matplotlib.image.imread(out_png).shape[0] > 200
    assert main(args) == 0  # deterministic policy, fixed placements: the same rows again
    assert [{k: v for k, v in r.items() if k != "seconds"} for r in json.loads(out_json.read_text())["rows"]] == \
           [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


def test_placements_are_held_out_from_the_evaluators():
    env = FunctionalGraspEnv("camera")
    test = placements(0, 20, 0.02, "test", clear=env.is_clear)
    assert not {p.offset for p in test} & {p.offset for p in placements(0, 100, 0.02, "rank") + placements(0, 10, 0.02, "eval")}


def test_a_run_directory_means_its_best_checkpoint(tmp_path, capsys):
    top = tmp_path / "run" / "evaluator" / "top"
    top.mkdir(parents=True)
    constant_policy(top / "policy-000002000.safetensors")
    (top / "index.json").write_text(json.dumps({"best": "policy-000002000.safetensors"}))
    assert main([str(tmp_path / "run"), "--episodes", "1"]) == 0
    assert "policy-000002000.safetensors" in capsys.readouterr().out


@pytest.mark.parametrize("extra, message", [
    (["--sweep", "gravity=1,2"], "KEY one of"),
    (["--sweep", "mass_scale=heavy"], "must be numbers"),
    (["--plot", "x.png"], "--plot needs --sweep"),
    (["--episodes", "0"], "at least 1"),
])
def test_bad_arguments_are_clear_errors(tmp_path, capsys, extra, message):
    policy = constant_policy(tmp_path / "p.safetensors")
    with pytest.raises(SystemExit) as exc:
        main([str(policy), *extra])
    assert exc.value.code == 2 and message in capsys.readouterr().err


def test_a_directory_without_a_best_checkpoint_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path)])
    assert exc.value.code == 2 and "neither a policy file" in capsys.readouterr().err
