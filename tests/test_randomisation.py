"""Training-time randomisation (issue 45): per-episode mass, torque-noise and jitter draws stay in their
ranges, reach the asymmetric critic's privileged state, are recorded in policy files, and an env
rebuilt from a policy file reproduces the conditions it was trained under."""

from __future__ import annotations

import numpy as np
import pytest

from forcegrasp.config import ConfigError, load_config
from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.runtime import make_env, policy_metadata


def test_draws_stay_in_their_ranges_and_reach_the_privileged_state():
    env = FunctionalGraspEnv("mug", mass_scale_range=(0.5, 5.0), torque_noise_range=(0.0, 0.5))
    masses, noises = [], []
    for seed in range(300):
        env.reset(seed=seed)
        masses.append(env.episode_mass_scale)
        noises.append(env.episode_noise_std)
        priv = env.privileged_state()
        assert priv[-2:] == pytest.approx((np.log(env.episode_mass_scale), env.episode_noise_std), abs=1e-6)
        body = env.ix.object_body
        assert env.model.body_mass[body] == pytest.approx(env._unit_mass * env.episode_mass_scale)
    masses, noises = np.array(masses), np.array(noises)
    assert masses.min() >= 0.5 and masses.max() <= 5.0 and noises.min() >= 0.0 and noises.max() <= 0.5
    # log-uniform mass: half the draws below the geometric mean (1.58x); uniform noise: mean 0.25
    assert 0.4 < np.mean(masses < np.sqrt(0.5 * 5.0)) < 0.6 and abs(noises.mean() - 0.25) < 0.04
    env.reset(seed=7)
    first = env.episode_mass_scale, env.episode_noise_std
    env.reset(seed=7)
    assert (env.episode_mass_scale, env.episode_noise_std) == first  # a placement's seed fixes its draws


def test_a_jitter_range_widens_the_placement_square_per_episode_and_tests_keep_the_fixed_one():
    env = FunctionalGraspEnv("mug", jitter_range=(0.02, 0.04))
    widths, offsets = [], []
    for seed in range(300):
        _, info = env.reset(seed=seed)
        widths.append(env.episode_jitter)
        offsets.append(info["offset"])
        assert np.all(np.abs(info["offset"]) <= env.episode_jitter)
        assert env.privileged_state()[0:2] == pytest.approx(100.0 * info["offset"])  # the critic sees the draw
    widths, offsets = np.array(widths), np.abs(np.array(offsets)).max(axis=1)
    assert widths.min() >= 0.02 and widths.max() <= 0.04 and abs(widths.mean() - 0.03) < 0.003
    assert np.mean(offsets > 0.02) > 0.15  # placements beyond the fixed ±2 cm square are trained on
    env.reset(seed=7)
    first = env.episode_jitter, env.offset.copy()
    env.reset(seed=7)
    assert env.episode_jitter == first[0] and np.array_equal(env.offset, first[1])
    # An explicit placement (every test) draws no width; a fixed jitter turns the recorded range off.
    env.reset(seed=8, options={"offset": (0.0, 0.0)})
    assert env.episode_jitter == first[0]
    config = load_config(env={}, overrides=["env.jitter_range=[0.02, 0.04]"])
    meta = policy_metadata(config, (16, 16))
    assert meta.extra["training_conditions"]["jitter_range"] == [0.02, 0.04]
    assert FunctionalGraspEnv.for_policy(meta).jitter_range == (0.02, 0.04)
    assert FunctionalGraspEnv.for_policy(meta, jitter=0.03).jitter_range is None
    with pytest.raises(ConfigError, match="jitter_range"):
        load_config(env={}, overrides=["env.jitter_range=[0.04, 0.02]"])


def test_a_drawn_mass_is_the_mass_an_env_built_at_it_has():
    built = FunctionalGraspEnv("camera", mass_scale=1.0)
    drawn = FunctionalGraspEnv("camera", mass_scale=5.0)
    drawn.set_mass_scale(1.0)
    for name in ("body_mass", "body_inertia", "body_subtreemass", "dof_invweight0"):
        assert np.allclose(getattr(built.model, name), getattr(drawn.model, name), rtol=1e-9, atol=1e-12), name
    # Before contact the two step identically (contact dynamics would amplify float rounding).
    for env in (built, drawn):
        env.reset(seed=0, options={"offset": (0.0, 0.0)})
    for _ in range(5):
        a, b = built.step(np.zeros(7))[0], drawn.step(np.zeros(7))[0]
        assert np.allclose(a, b, atol=1e-6)


def test_without_ranges_every_episode_has_the_fixed_conditions():
    env = FunctionalGraspEnv("mug", mass_scale=1.0, torque_noise_std=0.2)
    for seed in range(5):
        env.reset(seed=seed)
        assert (env.episode_mass_scale, env.episode_noise_std) == (1.0, 0.2)


@pytest.mark.parametrize("bad", [[5.0, 0.5], [0.0, 1.0], [1.0], [1.0, 2.0, 3.0], ["a", 2]])
def test_bad_ranges_are_configuration_errors(bad):
    with pytest.raises(ConfigError, match="mass_scale_range"):
        load_config(env={}, overrides=[f"env.mass_scale_range={bad!r}".replace("'", '"')])


def test_a_policy_file_records_its_training_conditions_and_an_env_rebuilt_from_it_reproduces_them():
    config = load_config(env={}, overrides=["env.object=mug", "env.mass_scale_range=[0.5, 5]",
                                            "env.torque_noise_range=[0, 0.5]", "env.jitter=0.025"])
    meta = policy_metadata(config, (16, 16))
    recorded = meta.extra["training_conditions"]
    assert recorded["mass_scale_range"] == [0.5, 5.0] and recorded["torque_noise_range"] == [0.0, 0.5]
    rebuilt = FunctionalGraspEnv.for_policy(meta)
    trained = make_env(config)
    assert (rebuilt.mass_scale_range, rebuilt.torque_noise_range, rebuilt.jitter) == \
        (trained.mass_scale_range, trained.torque_noise_range, trained.jitter) == ((0.5, 5.0), (0.0, 0.5), 0.025)
    for env in (rebuilt, trained):
        env.reset(seed=11)
    assert (rebuilt.episode_mass_scale, rebuilt.episode_noise_std) == (trained.episode_mass_scale, trained.episode_noise_std)
    # A fixed value given for a test overrides the recorded range: a test condition never randomises.
    fixed = FunctionalGraspEnv.for_policy(meta, mass_scale=1.0, torque_noise_std=0.5)
    fixed.reset(seed=3)
    assert (fixed.mass_scale_range, fixed.torque_noise_range) == (None, None)
    assert (fixed.episode_mass_scale, fixed.episode_noise_std) == (1.0, 0.5)
