"""The optional torque history (issue 10's lever outside Table I): the env appends the torques of
the k previous steps, policy files record the longer layout, everything that rebuilds an env for a
file gets the same, and nothing of another layout is taken silently."""

import numpy as np
import pytest

from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.policy import Policy
from forcegrasp.policy_file import load_policy_file
from forcegrasp.task import check_policy, obs_dim, observation_layout, torque_history_of


def test_layout_adds_the_history_after_the_torques_and_keeps_table_one():
    layout = observation_layout(True, 3)
    assert layout[0] == ("joint_torques", 24) and layout[1] == ("torque_history", 72)
    assert layout[:1] + layout[2:] == observation_layout(True)  # the rest is Table I, in order
    assert obs_dim(True, 3) == 77 + 72 and obs_dim(True, 0) == 77 and obs_dim(False) == 53
    for bad in (-1, 1.5):
        with pytest.raises(ValueError, match="whole number"):
            observation_layout(True, bad)
    with pytest.raises(ValueError, match="needs force_feedback"):
        observation_layout(False, 2)


def test_env_history_holds_the_previous_readings_newest_first():
    """Same seed and actions: the Table I part equals a plain env's observation step by step, and
    the history is the torque readings of the steps before, newest first (copies at reset)."""
    k = 2
    plain, hist = FunctionalGraspEnv("camera"), FunctionalGraspEnv("camera", torque_history=k)
    assert hist.observation_space.shape == (77 + 24 * k,)
    o0, _ = plain.reset(seed=3)
    o1, _ = hist.reset(seed=3)
    table = np.r_[0:24, 24 + 24 * k:77 + 24 * k]
    assert np.array_equal(o1[table], o0)
    assert np.array_equal(o1[24:48], o0[:24]) and np.array_equal(o1[48:72], o0[:24])
    readings = [o0[:24].copy()]
    rng = np.random.default_rng(0)
    for _ in range(6):
        action = rng.uniform(-0.3, 0.3, 7).astype(np.float32)
        p, *_ = plain.step(action)
        h, *_ = hist.step(action)
        assert np.array_equal(h[table], p)
        assert np.array_equal(h[24:48], readings[-1])
        assert np.array_equal(h[48:72], readings[-2] if len(readings) > 1 else readings[-1])
        readings.append(p[:24].copy())
    assert not np.array_equal(readings[1], readings[-1])  # the torques did change: the check has teeth
    # A new episode does not carry the old one's readings.
    o2, _ = hist.reset(seed=4)
    assert np.array_equal(o2[24:48], o2[:24]) and np.array_equal(o2[48:72], o2[:24])
    with pytest.raises(ValueError, match="needs force_feedback"):
        FunctionalGraspEnv("camera", force_feedback=False, torque_history=1)


def test_the_history_travels_in_policy_files_and_is_checked(tmp_path):
    """A learner configured with it writes files of the longer layout; the env rebuilt for the file
    has the history and the policy runs on it; an env of the other layout refuses the file."""
    from forcegrasp.config import ConfigError, load_config
    from forcegrasp_learner.learner import LearnerService

    config = load_config(overrides=[f"run.output_dir={tmp_path}", "run.name=hist", "learner.sac.hidden=[8, 8]",
                                    "learner.sac.buffer_size=1000", "env.object=camera", "env.torque_history=2"])
    path = LearnerService(config).save_policy()
    _, meta = load_policy_file(path)
    assert torque_history_of(meta) == 2 and meta.obs_dim == 77 + 48
    env = FunctionalGraspEnv.for_policy(meta)
    obs, _ = env.reset(seed=0)
    assert env.torque_history == 2 and Policy.load(path)(obs, deterministic=True).shape == (7,)
    check_policy(meta, "camera", True, config.env.action_steps(), 2)
    with pytest.raises(ValueError, match="gives 77"):
        check_policy(meta, "camera", True, config.env.action_steps())
    _, plain = load_policy_file(LearnerService(load_config(overrides=[
        f"run.output_dir={tmp_path}", "run.name=plain", "learner.sac.hidden=[8, 8]", "learner.sac.buffer_size=1000",
        "env.object=camera"])).save_policy())
    assert torque_history_of(plain) == 0
    with pytest.raises(ValueError, match="torque_history=2 gives 125"):
        check_policy(plain, "camera", True, config.env.action_steps(), 2)
    with pytest.raises(ConfigError, match="torque_history needs env.force_feedback"):
        load_config(overrides=["env.torque_history=1", "env.force_feedback=false"])


def test_an_actor_refuses_weights_of_another_history(tmp_path):
    """Weights of the plain layout reaching an actor whose envs keep a history (an extra actor
    started with another configuration) are refused, not acted on."""
    from forcegrasp.acting import Actor
    from forcegrasp.config import load_config
    from forcegrasp_learner.learner import LearnerService

    plain = load_config(overrides=[f"run.output_dir={tmp_path}", "run.name=plain", "learner.sac.hidden=[8, 8]",
                                   "learner.sac.buffer_size=1000", "env.object=camera"])
    weights, meta = load_policy_file(LearnerService(plain).save_policy())
    actor = Actor(load_config(env={}, overrides=["env.object=camera", "actor.envs_per_actor=1", "env.torque_history=1"]),
                  "a", seed=0)
    with pytest.raises(ValueError, match="policy is 77->7, env is 101->7"):
        actor.update(weights, meta, 1)
    assert actor.policy is None
