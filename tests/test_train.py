"""The single-process trainer writes real checkpoints and resumes with its step counter."""

import csv
import subprocess
import sys

import numpy as np

from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.policy import Policy


def _train(run_dir, steps):
    cmd = [
        sys.executable, "-m", "forcegrasp.cli", "train", "camera", "--steps", str(steps), "--run-dir", str(run_dir),
        "--learning-starts", "50", "--hidden", "32", "32", "--batch-size", "32", "--checkpoint-every", "100",
        "--eval-episodes", "1", "--log-every", "50",
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def test_train_checkpoints_and_resumes(tmp_path):
    run = tmp_path / "run"
    first = _train(run, 200)
    assert first.returncode == 0, first.stderr
    assert "step      200/200" in first.stdout
    second = _train(run, 300)
    assert second.returncode == 0, second.stderr
    assert "resumed" in second.stdout and "at step 200" in second.stdout
    assert "step      250/300" in second.stdout  # the counter continues, it does not restart at 50
    with (run / "progress.csv").open() as f:
        assert [int(float(r["step"])) for r in csv.DictReader(f)] == [100, 200, 300]
    assert (run / "curve.png").stat().st_size > 1000
    policy = Policy.load(run / "policy.safetensors")
    assert policy.metadata.object_name == "camera" and policy.metadata.training_steps == 300
    obs, _ = FunctionalGraspEnv("camera").reset(seed=0)
    action = policy(obs)
    assert action.shape == (7,) and np.all(np.abs(action) <= 1)
