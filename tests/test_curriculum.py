"""The randomisation curriculum (issue 45): envs start at the fixed training conditions, and an
actor opens the ranges one stage at a time, only after a window of successful policy episodes."""

from __future__ import annotations

import numpy as np
import pytest

from forcegrasp.acting import Actor
from forcegrasp.config import ConfigError, load_config
from forcegrasp.curriculum import RandomisationCurriculum
from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.runtime import policy_metadata
from forcegrasp.sampling import widened


def test_widened_moves_each_bound_from_the_fixed_value_to_the_full_range():
    assert widened(5.0, (0.5, 5.0), 0.0, log=True) == pytest.approx((5.0, 5.0))
    assert widened(5.0, (0.5, 5.0), 1.0, log=True) == pytest.approx((0.5, 5.0))
    assert widened(5.0, (0.5, 5.0), 0.5, log=True) == pytest.approx((np.sqrt(2.5), 5.0))  # geometric
    assert widened(0.0, (0.0, 0.5), 0.4) == pytest.approx((0.0, 0.2))
    assert widened(1.0, (2.0, 4.0), 0.5) == pytest.approx((1.5, 2.5))  # a fixed value outside the range


def test_the_gate_opens_a_stage_only_after_a_full_window_at_the_threshold():
    c = RandomisationCurriculum(threshold=0.75, window=4, steps=2)
    assert [c.record(s) for s in (True, True, True)] == [False] * 3 and c.level == 0.0  # window not full
    assert c.record(False) is True and c.level == 0.5  # (T, T, T, F): 3 of 4 reach 0.75, stage 1 of 2 opens
    assert [c.record(s) for s in (True, False, False, True)] == [False] * 4 and c.level == 0.5  # a fresh window
    # The window slides: (F, F, T, T) is 0.5, (F, T, T, T) opens the last stage.
    assert [c.record(True) for _ in range(2)] == [False, True] and c.level == 1.0
    assert c.record(True) is False and c.level == 1.0  # never beyond the full ranges
    with pytest.raises(ValueError, match="threshold"):
        RandomisationCurriculum(threshold=0.0, window=4, steps=2)


def test_an_env_draws_from_the_open_part_of_its_ranges():
    env = FunctionalGraspEnv("mug", mass_scale=5.0, mass_scale_range=(0.5, 5.0), torque_noise_range=(0.0, 0.5))
    env.randomisation_level = 0.0
    for seed in range(5):
        env.reset(seed=seed)
        assert (env.episode_mass_scale, env.episode_noise_std) == pytest.approx((5.0, 0.0))
    env.randomisation_level = 0.5
    draws = []
    for seed in range(200):
        env.reset(seed=seed)
        draws.append((env.episode_mass_scale, env.episode_noise_std))
    mass, noise = np.array(draws).T
    assert mass.min() >= np.sqrt(0.5 * 5.0) - 1e-9 and mass.max() <= 5.0 and noise.max() <= 0.25
    assert mass.min() < 1.8 and noise.max() > 0.2  # and the open half is really used


def _config(*extra):
    return load_config(env={}, overrides=["env.object=mug", "env.mass_scale_range=[0.5, 5]",
                                          "env.torque_noise_range=[0, 0.5]", "actor.envs_per_actor=2",
                                          "actor.demo_episodes=0", "actor.random_steps=0", *extra])


def test_an_actor_opens_the_ranges_as_its_policy_episodes_succeed():
    actor = Actor(_config("env.curriculum_success=1", "env.curriculum_window=2", "env.curriculum_stages=4"), "actor-0")
    assert [env.randomisation_level for env in actor.envs] == [0.0, 0.0]
    assert actor.stats()["curriculum_level"] == 0.0
    # Two successful policy episodes fill the window at the threshold (all of them): stage 1 of 4 opens in every env.
    for _ in range(2):
        actor.curriculum.record(True)
    actor._set_level()
    assert [env.randomisation_level for env in actor.envs] == [0.25, 0.25]
    # Played for real: every policy episode is counted, and random actions never make a window of
    # two successes, so the level holds.
    while actor.episodes < 6:
        actor.step()
    assert actor.curriculum.episodes == 2 + actor.episodes and actor.successes == 0
    assert [env.randomisation_level for env in actor.envs] == [0.25, 0.25]
    actor.close()


def test_without_the_curriculum_the_full_ranges_are_open_from_the_first_episode():
    actor = Actor(_config(), "actor-0")
    assert actor.curriculum is None and "curriculum_level" not in actor.stats()
    assert [env.randomisation_level for env in actor.envs] == [1.0, 1.0]
    actor.close()


def test_a_policy_file_records_the_curriculum():
    meta = policy_metadata(_config("env.curriculum_success=0.7"), (16, 16))
    assert meta.extra["randomisation_curriculum"] == {"success": 0.7, "window": 100, "stages": 5}
    assert "randomisation_curriculum" not in policy_metadata(_config(), (16, 16)).extra
    FunctionalGraspEnv.for_policy(meta)  # the record is not an env keyword


@pytest.mark.parametrize("bad, message", [
    (["env.curriculum_success=1.5"], "curriculum_success"),
    (["env.curriculum_success=-0.1"], "curriculum_success"),
    (["env.curriculum_window=0"], "curriculum_window"),
])
def test_bad_curriculum_settings_are_configuration_errors(bad, message):
    with pytest.raises(ConfigError, match=message):
        _config(*bad)


def test_a_curriculum_without_a_range_to_open_is_a_configuration_error():
    with pytest.raises(ConfigError, match="needs env.mass_scale_range"):
        load_config(env={}, overrides=["env.curriculum_success=0.7", "env.mass_scale_range=[]",
                                       "env.torque_noise_range=[]", "env.jitter_range=[]"])


def test_the_learner_reports_how_far_the_recent_draws_reach(tmp_path):
    """The learner reads each batch's privileged "domain" (ln mass scale, noise sigma): its stats and
    TensorBoard say the lightest mass and largest noise of the recent transitions, so a record shows
    how far a curriculum had opened the ranges at each mark."""
    from forcegrasp import task
    from forcegrasp.protocol import TransitionBatch, encode_transitions
    from forcegrasp_learner.learner import LearnerService

    config = _config(f"run.output_dir={tmp_path}", "learner.sac.hidden=[8, 8]", "learner.sac.privileged_critic=true")
    learner = LearnerService(config)
    rng = np.random.default_rng(0)
    priv = rng.standard_normal((6, task.PRIV_DIM)).astype(np.float32)
    mass, noise = np.array([5.0, 2.0, 0.8, 5.0, 1.0, 3.0]), np.array([0.0, 0.1, 0.3, 0.0, 0.05, 0.2])
    priv[:, task.DOMAIN] = np.stack([np.log(mass), noise], axis=1)
    batch = TransitionBatch("actor-0", 0, 0, rng.standard_normal((6, 77)), rng.uniform(-1, 1, (6, 7)),
                            rng.standard_normal(6), rng.standard_normal((6, 77)), np.zeros(6, bool), np.zeros(6, bool),
                            objects=["mug"], object_index=np.zeros(6, np.uint8), privileged=priv, next_privileged=priv)
    assert learner.ingest(learner.keys.transitions("actor-0"), encode_transitions(batch)) == 6
    stats = learner.stats(1.0, 0, 0)
    assert stats["mass_scale_min"] == pytest.approx(0.8) and stats["noise_std_max"] == pytest.approx(0.3)
