"""`forcegrasp train`: the learner, actor and evaluator roles in one process write a real run
directory (the same files as `forcegrasp up`) and resume with the step counter continuing."""

import re
import subprocess
import sys

import numpy as np

from forcegrasp.config import load_config
from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.policy import Policy
from forcegrasp.rundir import RunDir

SETTINGS = ["learner.sac.learning_starts=100", "learner.sac.hidden=[32, 32]", "learner.sac.batch_size=32",
            "actor.envs_per_actor=2", "evaluator.eval_every=200", "evaluator.eval_episodes=2",
            "evaluator.final_rank_episodes=2", "learner.stats_every_s=0.5", "learner.checkpoint_every=1000000"]


def _train(run_dir, steps):
    cmd = [sys.executable, "-m", "forcegrasp.cli", "train", "camera", "--steps", str(steps), "--run-dir", str(run_dir)]
    for kv in SETTINGS:
        cmd += ["--set", kv]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def test_train_checkpoints_resumes_and_evaluates(tmp_path):
    run = tmp_path / "run"
    first = _train(run, 400)
    assert first.returncode == 0, first.stderr[-3000:]
    assert re.search(r"step\s+\d+/400", first.stdout)
    files = RunDir(run)
    done = Policy.load(files.latest_policy).metadata.training_steps
    assert done >= 400 and files.checkpoint.exists() and files.replay.exists()
    second = _train(run, 700)
    assert second.returncode == 0, second.stderr[-3000:]
    assert f"resumed {run} at step {done}" in second.stdout
    steps = [int(s) for s in re.findall(r"step\s+(\d+)/700", second.stdout)]
    assert steps and min(steps) > done  # the counter continues, it does not restart at 0
    policy = Policy.load(files.latest_policy)
    assert policy.metadata.object_name == "camera" and policy.metadata.training_steps >= 700
    obs, _ = FunctionalGraspEnv("camera").reset(seed=0)
    action = policy(obs)
    assert action.shape == (7,) and np.all(np.abs(action) <= 1)
    # The evaluator role ran beside training: snapshots scored, a best policy on disk.
    index = files.read_index()
    assert index is not None and index["best"] is not None and len(index["history"]) >= 2
    assert (files.top / index["best"]).is_file()


def test_train_writes_the_policy_metadata_the_services_write(tmp_path):
    """Same configuration, same contract: every field a user or an actor relies on is equal."""
    from forcegrasp_learner.learner import LearnerService

    run = tmp_path / "run"
    assert _train(run, 200).returncode == 0
    trained = Policy.load(RunDir(run).latest_policy).metadata
    config = load_config(overrides=["env.object=camera", "run.name=svc", f"run.output_dir={tmp_path}", *SETTINGS])
    served = LearnerService(config).metadata()
    for field in ("obs_layout", "action_layout", "hidden", "object_name", "force_feedback", "action_low",
                  "action_high", "obs_norm"):
        assert getattr(trained, field) == getattr(served, field), field
    assert trained.action_low and trained.action_high  # the action scaling travels with the file
