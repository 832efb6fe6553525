"""Commanded proprioception (issue 46's lever outside Table I): the same slots filled with what the
policy commanded, so that without force feedback nothing observed depends on the object; policy
files record the mode through their observation layout, and nothing of the other mode is taken
silently."""

import numpy as np
import pytest

from forcegrasp.config import ConfigError, load_config
from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.policy import Actor, Policy
from forcegrasp.policy_file import load_policy_file
from forcegrasp.runtime import policy_metadata
from forcegrasp.task import (
    COMMANDED_SLOTS,
    OBS_LAYOUT,
    check_policy,
    obs_dim,
    observation_layout,
    proprioception_of,
)

CLOSE = np.array([0, 0, 0, 0, 0, 0, 1.0], np.float32)  # close the hand where it stands: it meets the object
OFFSETS = ((0.0, 0.0), (0.015, -0.01))
COMMANDED_NAMES = ["joint_torques", "joint_targets", "base_command", "h_command", "base_targets",
                   "prev_base_command", "prev_h_command", "goal_pose", "goal_palm"]


def test_layout_of_each_mode():
    measured = observation_layout(True)
    assert measured == OBS_LAYOUT == observation_layout(True, 0, "measured")
    commanded = observation_layout(True, 0, "commanded")
    assert [n for n, _ in commanded] == COMMANDED_NAMES
    assert [s for _, s in commanded] == [s for _, s in measured]  # same sizes, same order
    assert observation_layout(False, 0, "commanded") == commanded[1:]
    for mode in ("measured", "commanded"):
        assert obs_dim(True, 0, mode) == 77 and obs_dim(False, 0, mode) == 53 and obs_dim(True, 2, mode) == 77 + 48
    history = observation_layout(True, 1, "commanded")
    assert history[:2] == (("joint_torques", 24), ("torque_history", 24)) and history[2:] == commanded[1:]
    assert set(COMMANDED_SLOTS.values()).isdisjoint(n for n, _ in OBS_LAYOUT)  # the names tell the modes apart
    with pytest.raises(ValueError, match="measured, commanded"):
        observation_layout(True, 0, "foo")


def _episodes(force_feedback: bool, proprioception: str):
    """Observations of two episodes with the object at the two offsets under the same closing
    actions, up to the step where either ends, and whether the hand touched the object in either."""
    envs = [FunctionalGraspEnv("mug", force_feedback=force_feedback, proprioception=proprioception) for _ in OFFSETS]
    assert all(env.is_clear(offset) for env, offset in zip(envs, OFFSETS))
    obs = [env.reset(seed=0, options={"offset": offset})[0] for env, offset in zip(envs, OFFSETS)]
    pairs, touched, done = [tuple(obs)], [False], False
    while not done:
        steps = [env.step(CLOSE) for env in envs]
        pairs.append(tuple(s[0] for s in steps))
        touched.append(any(env.privileged_state()[13] > 0 for env in envs))  # PRIVILEGED_LAYOUT hand_contact
        done = any(s[2] or s[3] for s in steps)
    return envs, pairs, touched


def test_commanded_without_force_feedback_sees_nothing_of_the_object():
    envs, pairs, touched = _episodes(False, "commanded")
    assert any(touched), "the hand never touched the object: the test has no teeth"
    for t, (a, b) in enumerate(pairs):
        assert np.array_equal(a, b), f"step {t}: the observation depends on where the object is"
    # The slots hold the commands: J(h_cmd), the base targets (now and one step ago), h_cmd.
    env, obs = envs[0], pairs[-1][0]
    at = env._slots
    n, dh = len(pairs) - 1, CLOSE[6] * env._action_scale[6]  # steps taken, h_cmd's increment per step
    h_cmd = min(1.0, dh * n)
    assert obs[at["h_command"]][0] == pytest.approx(h_cmd)
    assert obs[at["prev_h_command"]][0] == pytest.approx(min(1.0, dh * (n - 1)))
    np.testing.assert_allclose(obs[at["joint_targets"]], h_cmd * (env._Jg - env._J0) + env._J0, atol=1e-6)
    np.testing.assert_allclose(obs[at["base_command"]], env.label.pregrasp.base, atol=1e-6)
    np.testing.assert_array_equal(obs[at["base_command"]], obs[at["base_targets"]])
    np.testing.assert_array_equal(obs[at["prev_base_command"]], obs[at["base_targets"]])  # no base motion
    first = pairs[0][0]
    np.testing.assert_allclose(first[at["joint_targets"]], env._J0, atol=1e-6)
    assert first[at["h_command"]][0] == first[at["prev_h_command"]][0] == 0.0
    # The measured mode, same actions, does show the object: what this mode takes away.
    _, measured, _ = _episodes(False, "measured")
    assert any(not np.array_equal(a, b) for a, b in measured)


def test_commanded_with_force_feedback_still_feels_the_torques():
    envs, pairs, touched = _episodes(True, "commanded")
    assert any(touched)
    torques = envs[0]._slots["joint_torques"]
    rest = np.r_[torques.stop:77]
    for a, b in pairs:
        assert np.array_equal(a[rest], b[rest])  # only the measured torques may differ
    contact = touched.index(True)
    assert any(not np.array_equal(a[torques], b[torques]) for a, b in pairs[contact:]), \
        "the torques did not tell the two placements apart after contact"


def test_policy_files_record_the_mode_and_are_checked(tmp_path):
    config = load_config(env={}, overrides=["env.object=camera", "env.proprioception=commanded"])
    assert config.env.proprioception == "commanded"
    meta = policy_metadata(config, (8, 8))
    assert proprioception_of(meta) == "commanded" and meta.obs_dim == 77
    assert [n for n, _ in meta.obs_layout] == COMMANDED_NAMES
    path = Policy.from_actor(Actor(meta.obs_dim, meta.act_dim, hidden=(8, 8)), meta, seed=0).save(tmp_path / "c.safetensors")
    _, loaded = load_policy_file(path)
    assert proprioception_of(loaded) == "commanded"
    env = FunctionalGraspEnv.for_policy(loaded)
    assert env.proprioception == "commanded" and "joint_targets" in env._slots
    obs, _ = env.reset(seed=0)
    assert Policy.load(path)(obs, deterministic=True).shape == (7,)
    steps = config.env.action_steps()
    check_policy(loaded, "camera", True, steps, 0, "commanded")
    with pytest.raises(ValueError, match="policy observes commanded proprioception.*proprioception=measured"):
        check_policy(loaded, "camera", True, steps)
    measured = policy_metadata(load_config(env={}, overrides=["env.object=camera"]), (8, 8))
    assert proprioception_of(measured) == "measured"
    assert FunctionalGraspEnv.for_policy(measured).proprioception == "measured"
    with pytest.raises(ValueError, match="policy observes measured proprioception.*observes commanded"):
        check_policy(measured, "camera", True, steps, 0, "commanded")
    no_ff = policy_metadata(load_config(env={}, overrides=["env.object=camera", "env.force_feedback=false",
                                                           "env.proprioception=commanded"]), (8, 8))
    assert proprioception_of(no_ff) == "commanded" and no_ff.obs_dim == 53
    with pytest.raises(ValueError, match="gives 77"):  # another size: the size is what it says
        check_policy(no_ff, "camera", True, steps, 0, "commanded")


def test_the_evaluator_and_an_actor_refuse_the_other_mode(tmp_path):
    from forcegrasp.acting import Actor as ActorRole
    from forcegrasp.policy_file import actor_param_shapes, policy_to_bytes
    from forcegrasp.ranking import CheckpointRejected
    from forcegrasp_evaluator.evaluator import EvaluatorService

    base = [f"run.output_dir={tmp_path / 'runs'}", "env.object=camera", "evaluator.http_port=0",
            "actor.envs_per_actor=1"]
    commanded = load_config(env={}, overrides=[*base, "run.name=cmd", "env.proprioception=commanded"])
    measured = load_config(env={}, overrides=[*base, "run.name=meas"])
    meta = policy_metadata(measured, (8, 8))
    weights = {k: np.zeros(s, np.float32) for k, s in actor_param_shapes(meta).items()}
    with EvaluatorService(commanded, log_episodes=False) as service:
        assert service.protocol()["proprioception"] == "commanded"
        with pytest.raises(CheckpointRejected, match="measured proprioception.*proprioception=commanded"):
            service._check(policy_to_bytes(weights, meta), "policy-1")
        own = policy_metadata(commanded, (8, 8))
        service._check(policy_to_bytes(weights, own), "policy-2")
    actor = ActorRole(commanded, "a", seed=0)
    with pytest.raises(ValueError, match="measured proprioception, the envs commanded"):
        actor.update(weights, meta, 1)
    assert actor.policy is None and actor.update(weights, policy_metadata(commanded, (8, 8)), 1)


def test_bad_values_are_clear_errors():
    with pytest.raises(ConfigError, match="env.proprioception = 'foo' must be one of measured, commanded"):
        load_config(env={}, overrides=["env.proprioception=foo"])
    with pytest.raises(ValueError, match="proprioception must be one of measured, commanded, got 'foo'"):
        FunctionalGraspEnv("camera", proprioception="foo")
    assert load_config(env={}).env.proprioception == "measured"
    assert FunctionalGraspEnv("camera").proprioception == "measured"
