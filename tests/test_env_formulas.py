"""The paper's formulas on constructed states, and the env's observation/action wiring."""

import numpy as np
import pytest

from forcegrasp.env import OBS_LAYOUT, FunctionalGraspEnv, RewardWeights, evaluate_state, observed_h


def test_observed_h_uses_the_largest_range_normalised_difference():
    goal = np.array([0.0, 1.0, 0.5])
    span = np.array([2.0, 1.0, 0.5])
    joints = np.array([1.0, 0.9, 0.5])  # normalised diffs 0.5, 0.1, 0
    assert observed_h(joints, goal, span) == pytest.approx(1 - 0.5 * 0.5)
    assert observed_h(goal, goal, span) == 1.0


def test_reward_is_weighted_sum_of_the_three_terms():
    out = evaluate_state(
        h=0.9,
        palm_rel=np.array([0.03, 0.0, 0.0]),
        goal_palm_rel=np.zeros(3),
        object_pos=np.array([0.0, 0.004, 0.0]),
        object_start=np.zeros(3),
        step=7,
    )
    assert out.r_a == pytest.approx(-0.1)
    assert out.r_b == pytest.approx(-0.03)
    assert out.r_c == pytest.approx(-0.004)
    assert out.reward == pytest.approx(1.5 - 0.1 - 20 * 0.03 - 100 * 0.004)
    assert not out.success and out.failure is None


def test_success_adds_bonus_and_step_reward():
    out = evaluate_state(0.97, np.array([0.005, 0, 0]), np.zeros(3), np.array([0.002, 0, 0]), np.zeros(3), step=50)
    base = 1.5 - 0.03 - 20 * 0.005 - 100 * 0.002
    assert out.success and out.failure is None
    assert out.reward == pytest.approx(base + 1000 + 1.5 * (200 - 50))


@pytest.mark.parametrize(
    "h, palm, obj, expect",
    [
        (0.97, 0.005, 0.011, "object_moved"),  # object beyond 1 cm fails even when close otherwise
        (0.5, 0.101, 0.0, "palm_deviation"),
        (0.94, 0.005, 0.002, None),  # |ra| = 0.06 misses success but is no failure
        (0.97, 0.0101, 0.002, None),  # palm just outside 1 cm: not yet a success
    ],
)
def test_terminal_conditions(h, palm, obj, expect):
    out = evaluate_state(h, np.array([palm, 0, 0]), np.zeros(3), np.array([0, obj, 0]), np.zeros(3), step=3)
    assert out.failure == expect
    assert not out.success


def test_lighter_object_tolerance_is_a_parameter():
    args = (0.5, np.zeros(3), np.zeros(3), np.array([0.02, 0, 0]), np.zeros(3), 3)
    assert evaluate_state(*args).failure == "object_moved"
    assert evaluate_state(*args, object_tolerance=0.03).failure is None


def test_custom_weights_are_used():
    w = RewardWeights(w=0.0, wa=2.0, wb=0.0, wc=0.0)
    out = evaluate_state(0.5, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), 1, weights=w)
    assert out.reward == pytest.approx(-1.0)


@pytest.fixture(scope="module")
def env():
    e = FunctionalGraspEnv("mug")
    yield e
    e.close()


def test_observation_layout_matches_table_one(env):
    obs, _ = env.reset(seed=3)
    assert obs.shape == (77,) and obs.dtype == np.float32
    assert sum(n for _, n in OBS_LAYOUT) == 77
    d, ix = env.data, env.ix
    sl = {}
    i = 0
    for name, n in OBS_LAYOUT:
        sl[name] = obs[i : i + n]
        i += n
    np.testing.assert_allclose(sl["joint_torques"], d.actuator_force[ix.hand_act], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(sl["joint_angles"], d.qpos[ix.hand_qpos], atol=1e-6)
    np.testing.assert_allclose(sl["hand_pose"], d.qpos[ix.base_qpos], atol=1e-6)
    np.testing.assert_allclose(sl["base_targets"], env.label.pregrasp.base, atol=1e-6)
    np.testing.assert_allclose(sl["goal_pose"], env.label.goal.base, atol=1e-6)
    np.testing.assert_allclose(sl["goal_palm"], env.label.goal_palm, atol=1e-6)
    expected_h = observed_h(d.qpos[ix.hand_qpos], env.label.goal.hand, ix.hand_range[:, 1] - ix.hand_range[:, 0])
    assert sl["h"][0] == pytest.approx(expected_h, abs=1e-6)


def test_action_moves_targets_and_hand_follows_the_interpolation(env):
    env.reset(seed=1)
    before = env.base_target.copy()
    action = np.array([1, -1, 0.5, 0, 0, -0.5, 1], dtype=np.float32)
    obs, reward, term, trunc, info = env.step(action)
    np.testing.assert_allclose(env.base_target - before, action[:6] * env._action_scale[:6], atol=1e-12)
    assert env.h_command == pytest.approx(env._action_scale[6])
    J0, Jg = env.label.pregrasp.hand, env.label.goal.hand
    np.testing.assert_allclose(env.data.ctrl[env.ix.hand_act], env.h_command * (Jg - J0) + J0, atol=1e-12)
    # The previous pose/h observed are the ones from before the step.
    prev_pose = obs[24 + 24 + 6 + 1 + 6 : 24 + 24 + 6 + 1 + 12]
    assert np.all(np.isfinite(obs)) and prev_pose.shape == (6,)
    for key in ("r_a", "r_b", "r_c", "h", "object_displacement", "palm_error", "success", "failure"):
        assert key in info
    assert reward == pytest.approx(1.5 + info["r_a"] + 20 * info["r_b"] + 100 * info["r_c"])


def test_force_feedback_off_removes_torques():
    e = FunctionalGraspEnv("mug", force_feedback=False)
    obs, _ = e.reset(seed=0)
    assert obs.shape == (53,) and e.observation_space.shape == (53,)
    np.testing.assert_allclose(obs[:24], e.data.qpos[e.ix.hand_qpos], atol=1e-6)


def test_torque_noise_has_the_documented_spread():
    e = FunctionalGraspEnv("mug", torque_noise_std=0.05)
    e.reset(seed=0)
    diffs = [e._observation()[:24] - e.data.actuator_force[e.ix.hand_act] for _ in range(200)]
    assert np.std(diffs) == pytest.approx(0.05, rel=0.1)
    assert abs(np.mean(diffs)) < 0.01


def test_jitter_stays_within_epsilon_and_object_starts_at_rest():
    e = FunctionalGraspEnv("camera", jitter=0.01)
    for seed in range(20):
        _, info = e.reset(seed=seed)
        assert np.all(np.abs(info["offset"]) <= 0.01)
        np.testing.assert_allclose(e.data.xpos[e.ix.object_body][:2], info["offset"], atol=1e-9)
    # A still hand leaves the object where it started: settling is not displacement.
    for _ in range(10):
        _, _, _, _, info = e.step(np.zeros(7, dtype=np.float32))
    assert info["object_displacement"] < 1e-3


def test_time_limit_truncates_and_low_return_aborts():
    e = FunctionalGraspEnv("camera", max_steps=5, abort_return=-1e9)
    e.reset(seed=0)
    for k in range(5):
        _, _, term, trunc, info = e.step(np.zeros(7, dtype=np.float32))
    assert trunc and not term and info["failure"] == "time_limit"
    e = FunctionalGraspEnv("camera", abort_return=100.0)  # any start is below: aborts at once
    e.reset(seed=0)
    _, _, term, trunc, info = e.step(np.zeros(7, dtype=np.float32))
    assert term and info["failure"] == "low_return"


def test_moving_away_fails_on_palm_deviation():
    e = FunctionalGraspEnv("camera", abort_return=-1e9)
    e.reset(seed=0)
    up = np.array([0, 1, 0, 0, 0, 0, 0], dtype=np.float32)  # ARTy raises the hand
    for _ in range(60):
        _, _, term, _, info = e.step(up)
        if term:
            break
    assert term and info["failure"] == "palm_deviation"
