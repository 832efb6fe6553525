"""Gymnasium contract, determinism and clear errors for bad input."""

import json

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import forcegrasp  # noqa: F401  (registers the ids)
from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.labels import LabelFileError, load_label, parse_label
from forcegrasp.objects import ObjectFileError, load_object, parse_object

IDS = ["FunctionalGrasp-SprayBottle-v0", "FunctionalGrasp-PowerDrill-v0", "FunctionalGrasp-Mug-v0", "FunctionalGrasp-Camera-v0",
       "FunctionalGrasp-MugMesh-v0"]  # every object file, an imported mesh too


@pytest.mark.parametrize("env_id", IDS)
def test_registered_ids_pass_gymnasium_env_checker(env_id):
    env = gym.make(env_id, mass_scale=1.0)
    check_env(env.unwrapped, skip_render_check=True)
    assert env.unwrapped.mass_scale == 1.0
    env.close()


def test_same_seed_gives_the_same_episode():
    def episode(seed):
        env = FunctionalGraspEnv("power_drill")
        env.action_space.seed(seed)
        obs, _ = env.reset(seed=seed)
        traj = [obs]
        for _ in range(30):
            obs, r, term, trunc, _ = env.step(env.action_space.sample())
            traj.append(np.append(obs, r))
            if term or trunc:
                break
        return traj

    a, b, c = episode(5), episode(5), episode(6)
    assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
    # The first observation cannot differ (the object's pose is not observed); the episode does.
    assert np.array_equal(a[0], c[0])
    assert any(not np.array_equal(x, y) for x, y in zip(a[1:], c[1:]))


def test_unknown_object_lists_the_valid_ones():
    with pytest.raises(ObjectFileError, match="valid objects: camera, mug, mug_mesh, power_drill, spray_bottle"):
        FunctionalGraspEnv("teapot")
    with pytest.raises(ObjectFileError, match="unknown object"):
        load_object("../objects/mug")


def test_malformed_object_file_names_the_field():
    good = json.loads(load_object("mug").path.read_text())
    cases = {
        "mass": ("mass", -1),
        "geoms[0].type": ("geoms", [{"name": "a", "type": "cone", "size": [1]}]),
        "geoms[0].size": ("geoms", [{"name": "a", "type": "box", "size": [0.1, 0.1]}]),
        "functional_part": ("functional_part", ["spout"]),
        "grasp_hint.palm_at": ("grasp_hint", {**good["grasp_hint"], "palm_at": [0, "x", 0]}),
    }
    for field, (key, value) in cases.items():
        raw = {**good, key: value}
        with pytest.raises(ObjectFileError, match=field.replace("[", r"\[").replace("]", r"\]")):
            parse_object(raw)
    raw = dict(good)
    del raw["geoms"]
    with pytest.raises(ObjectFileError, match="missing field 'geoms'"):
        parse_object(raw)


def test_malformed_label_file_names_the_field(tmp_path):
    good = load_label("mug").to_json()
    bad = json.loads(json.dumps(good))
    del bad["goal"]["hand"]["FFJ2"]
    with pytest.raises(LabelFileError, match=r"goal.hand.*FFJ2"):
        parse_label(bad)
    bad = json.loads(json.dumps(good))
    bad["goal_palm"] = [0, 0]
    with pytest.raises(LabelFileError, match="goal_palm"):
        parse_label(bad)
    bad = json.loads(json.dumps(good))
    bad["pregrasp"]["base"]["ARTx"] = "nan"
    with pytest.raises(LabelFileError, match="pregrasp.base"):
        parse_label(bad)
    path = tmp_path / "mug.json"
    path.write_text("{not json")
    with pytest.raises(LabelFileError, match="not readable JSON"):
        load_label("mug", path)


@pytest.mark.parametrize(
    "action, message",
    [
        ([np.nan, 0, 0, 0, 0, 0, 0], "finite"),
        ([0, 0, 0, 0, 0, 0, 1.5], r"\[-1, 1\]"),
        ([0, 0, 0], "shape"),
    ],
)
def test_bad_actions_get_a_clear_error_and_change_nothing(action, message):
    env = FunctionalGraspEnv("mug")
    env.reset(seed=0)
    qpos = env.data.qpos.copy()
    with pytest.raises(ValueError, match=message):
        env.step(np.array(action, dtype=np.float32))
    np.testing.assert_array_equal(env.data.qpos, qpos)
    assert env.steps == 0


def test_bad_parameters_get_a_clear_error():
    with pytest.raises(ValueError, match="mass_scale"):
        FunctionalGraspEnv("mug", mass_scale=0)
    with pytest.raises(ValueError, match="offset"):
        FunctionalGraspEnv("mug").reset(options={"offset": [0.1]})
