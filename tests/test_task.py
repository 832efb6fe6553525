"""The task contract: sizes from one place, checks of a policy against an env, light imports."""

import subprocess
import sys

import numpy as np
import pytest

from forcegrasp import task
from forcegrasp.env import FunctionalGraspEnv


def test_layouts_match_the_env():
    for ff in (True, False):
        env = FunctionalGraspEnv("mug", force_feedback=ff)
        assert env.observation_space.shape == (task.obs_dim(ff),) == ((77,) if ff else (53,))
        assert env.action_space.shape == (task.ACT_DIM,) == (7,)
        env.reset(seed=0)
        assert env.privileged_state().shape == (task.PRIV_DIM,)
        assert np.allclose(env._action_scale, task.action_scale())


def test_check_policy_names_the_mismatch():
    meta = task.policy_metadata("mug", True, (8, 8))
    task.check_policy(meta, "mug", True)
    with pytest.raises(ValueError, match="force_feedback=False gives 53"):
        task.check_policy(meta, "mug", False)
    with pytest.raises(ValueError, match="for object 'mug'"):
        task.check_policy(meta, "camera", True)
    meta.action_high = [1.0] * 7
    with pytest.raises(ValueError, match="action steps"):
        task.check_policy(meta, "mug", True)


def test_protocol_policy_and_task_load_neither_mujoco_nor_gymnasium():
    code = ("import sys, forcegrasp.protocol, forcegrasp.policy, forcegrasp.task, forcegrasp.runtime, "
            "forcegrasp_learner.learner\n"
            "heavy = [m for m in ('mujoco', 'gymnasium') if m in sys.modules]\n"
            "assert not heavy, heavy")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
