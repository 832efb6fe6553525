"""The torque filter (issue 45, a lever outside Table I): the observed torques are an exponential
moving average of the noisy readings, recorded in policy files and kept by every test of a policy."""

from __future__ import annotations

import numpy as np
import pytest

from forcegrasp.conditions import env_kwargs
from forcegrasp.config import ConfigError, load_config
from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.runtime import policy_metadata

TORQUES = slice(0, 24)


def _episode(env, seed=3, steps=40):
    obs, _ = env.reset(seed=seed, options={"offset": (0.0, 0.0)})
    out, forces = [obs[TORQUES].copy()], [env._hand_force.copy()]
    rng = np.random.default_rng(0)
    for _ in range(steps):
        obs = env.step(rng.uniform(-0.3, 0.6, 7))[0]
        out.append(obs[TORQUES].copy())
        forces.append(env._hand_force.copy())
    return np.array(out), np.array(forces)


def test_observed_torques_are_the_moving_average_of_the_readings():
    raw, forces = _episode(FunctionalGraspEnv("mug"))
    assert np.allclose(raw, forces, atol=1e-5)  # no filter: the reading itself (Table I)
    filtered, forces_f = _episode(FunctionalGraspEnv("mug", torque_filter=0.25))
    assert np.allclose(forces_f, forces)  # the filter changes what is observed, not the physics
    expected = [forces[0]]
    for f in forces[1:]:
        expected.append(0.25 * f + 0.75 * expected[-1])
    assert np.allclose(filtered, expected, atol=1e-5)


def test_the_filter_divides_the_noise_as_an_ema_does():
    noisy, forces = _episode(FunctionalGraspEnv("mug", torque_noise_std=0.5), steps=150)
    smooth, _ = _episode(FunctionalGraspEnv("mug", torque_noise_std=0.5, torque_filter=0.2), steps=150)
    raw_noise = (noisy - forces)[1:].std()
    assert raw_noise == pytest.approx(0.5, rel=0.1)
    # the filtered noise: 0.5 sqrt(a / (2 - a)) = 0.167 for a = 0.2 (the signal's own lag adds a little)
    assert (smooth[20:] - forces[20:]).std() < 0.3


def test_policy_files_record_the_filter_and_tests_keep_it():
    config = load_config(env={}, overrides=["env.object=mug", "env.torque_filter=0.3",
                                            "env.torque_noise_range=[0, 1]"])
    meta = policy_metadata(config, (8,))
    assert meta.extra["training_conditions"]["torque_filter"] == 0.3
    assert FunctionalGraspEnv.for_policy(meta).torque_filter == 0.3
    tested = FunctionalGraspEnv.for_policy(meta, **env_kwargs("noise_0.5"))
    assert tested.torque_filter == 0.3 and tested.torque_noise_std == 0.5 and tested.torque_noise_range is None
    unfiltered = policy_metadata(load_config(env={}, overrides=["env.object=mug"]), (8,))
    assert "torque_filter" not in unfiltered.extra["training_conditions"]
    assert FunctionalGraspEnv.for_policy(unfiltered).torque_filter == 1.0


@pytest.mark.parametrize("bad", [["env.torque_filter=0"], ["env.torque_filter=1.5"],
                                 ["env.torque_filter=0.5", "env.force_feedback=false"]])
def test_bad_filters_are_configuration_errors(bad):
    with pytest.raises(ConfigError, match="torque_filter"):
        load_config(env={}, overrides=bad)
    with pytest.raises(ValueError, match="torque_filter"):
        FunctionalGraspEnv("mug", torque_filter=0.0)


def test_the_actor_loss_sees_noisy_torques_and_the_critics_clean_ones():
    """``learner.sac.actor_torque_noise``: torque noise as an augmentation of the actor's loss only
    (sigma drawn per sample), so robustness to noise is learnt from clean episodes."""
    import torch

    from forcegrasp.sac import SAC, SACConfig
    from forcegrasp.task import TORQUES

    sac = SAC(77, 7, SACConfig(hidden=(8,), actor_torque_noise=1.0, seed=3))
    obs = torch.zeros(4000, 77)
    noisy = sac._noisy_torques(obs)
    assert torch.equal(noisy[:, 24:], obs[:, 24:]) and torch.equal(obs, torch.zeros(4000, 77))  # a copy
    per_sample = noisy[:, TORQUES].std(1)
    assert 0.0 < per_sample.min() < 0.2 and 0.8 < per_sample.max() < 1.7  # sigma ~ U(0, 1), one per sample
    assert abs(float(noisy[:, TORQUES].pow(2).mean()) - 1 / 3) < 0.03  # E[sigma^2] = 1/3
    seen = {}
    sac.actor_terms = lambda o, alpha, critic_obs: seen.update(actor=o, critic=critic_obs) or SAC.actor_terms(
        sac, o, alpha, critic_obs)
    batch = {"obs": np.zeros((16, 77), np.float32), "action": np.zeros((16, 7), np.float32),
             "reward": np.zeros(16, np.float32), "next_obs": np.zeros((16, 77), np.float32),
             "terminated": np.zeros(16, np.float32)}
    sac.update(batch)
    assert seen["actor"][:, TORQUES].abs().sum() > 0 and seen["critic"].abs().sum() == 0
    assert SAC(77, 7, SACConfig(hidden=(8,)))._noisy_torques(obs) is obs  # off by default
    with pytest.raises(ConfigError, match="actor_torque_noise needs env.force_feedback"):
        load_config(env={}, overrides=["learner.sac.actor_torque_noise=0.5", "env.force_feedback=false"])
    with pytest.raises(ConfigError, match="actor_torque_noise"):
        load_config(env={}, overrides=["learner.sac.actor_torque_noise=-1"])
