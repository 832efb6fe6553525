"""Grasp labels: the stored labels pass the checks of forcegrasp.label_checks (recomputed here, not
read back): the goal is a grasp that holds the object without the table, the pre-grasp is clear
over the whole jitter square, the scripted oracle solves the task, and labelling works for a
user-added object."""

import json
import os
import shutil
import subprocess
import sys

import mujoco
import numpy as np
import pytest

from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.evaluation import placements
from forcegrasp.label_checks import PALM_CLEARANCE_M, hold_check, lift_check, pregrasp_clearance, pregrasp_palm_error
from forcegrasp.labeling import hand_object_clearance
from forcegrasp.scene import ALL_JOINTS
from forcegrasp.labels import load_label
from forcegrasp.objects import list_objects, load_object
from forcegrasp.scene import SceneIndex, build_model, resting_height
from forcegrasp.scripted import jitter_offsets, success_rate

OBJECTS = ["spray_bottle", "power_drill", "mug", "camera", "mug_mesh"]


def test_every_object_has_a_label():
    assert sorted(OBJECTS) == list_objects()
    for name in OBJECTS:
        assert load_label(name).object == name


@pytest.mark.parametrize("name", OBJECTS)
@pytest.mark.parametrize("mass_scale", [1.0, 5.0])
def test_goal_grasp_touches_the_functional_part_and_holds(name, mass_scale):
    label = load_label(name)
    checks = hold_check(load_object(name), label.goal.q, mass_scale=mass_scale)
    assert checks["functional_contact"], checks
    assert checks["max_penetration_m"] < 0.002, checks
    assert checks["object_moved_m"] < 0.01, checks


@pytest.mark.parametrize("name", OBJECTS)
def test_goal_grasp_holds_the_object_without_the_table(name):
    """At 1x mass the hand alone keeps the object within 1 cm of its place in the palm for 1 s,
    the thumb and at least two other fingers on it."""
    checks = lift_check(load_object(name), load_label(name).goal.q, 1.0)
    assert checks["holds"], checks
    assert "th" in checks["fingers_in_contact"] and len(set(checks["fingers_in_contact"]) - {"th", "palm"}) >= 2


@pytest.mark.parametrize("name", OBJECTS)
def test_the_hold_check_fails_when_the_thumb_lets_go(name):
    """Take the thumb away (its servo targets straightened to 0) and the same check fails: the
    object falls, or what still touches it is no grasp by the rule (thumb and two more fingers)."""
    obj, label = load_object(name), load_label(name)
    thumb = {i: 0.0 for i, j in enumerate(ALL_JOINTS) if j.startswith("TH")}
    checks = lift_check(obj, label.goal.q, 1.0, hand_overrides=thumb)
    assert not checks["holds"] and "th" not in checks["fingers_in_contact"], checks


@pytest.mark.parametrize("name", OBJECTS)
def test_pregrasp_is_clear_over_the_whole_jitter_square(name):
    label = load_label(name)
    square = pregrasp_clearance(load_object(name), label.pregrasp.q, jitter=0.02, grid=7)
    assert square["clear"], square
    assert square["palm_distance_m"] >= 0.9 * PALM_CLEARANCE_M, square
    m = build_model(load_object(name))
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    d.qpos[ix.all_qpos] = label.pregrasp.q
    d.qpos[ix.object_qpos + 2] = resting_height(m)
    d.qpos[ix.object_qpos + 3] = 1.0
    mujoco.mj_forward(m, d)
    hand, obj = set(ix.hand_geoms), set(ix.object_geoms)
    touching = [c for c in d.contact[: d.ncon] if {c.geom1, c.geom2} & hand and {c.geom1, c.geom2} & obj]
    assert not touching


@pytest.mark.parametrize("name", OBJECTS)
def test_pregrasp_palm_starts_inside_the_palm_tolerance_everywhere(name):
    """Else the env would fail some placements at their first step, before the policy acts."""
    label = load_label(name)
    m = build_model(load_object(name))
    reach = pregrasp_palm_error(m, label.pregrasp.q, label.goal_palm, jitter=0.02)
    assert reach["within_palm_tolerance"], reach
    env = FunctionalGraspEnv(name)
    for corner in ((0.02, 0.02), (0.02, -0.02), (-0.02, 0.02), (-0.02, -0.02)):
        env.reset(options={"offset": corner})
        _, _, terminated, _, info = env.step(np.zeros(env.action_space.shape, np.float32))
        assert not terminated and info["palm_error"] < env.palm_tolerance, (corner, info)


@pytest.mark.parametrize("name", OBJECTS)
def test_scripted_oracle_solves_jittered_placements(name):
    """Told the true offset, the straight approach succeeds on >= 95 % of 50 placements."""
    env = FunctionalGraspEnv(name)
    rate, results = success_rate(env, jitter_offsets(50, seed=1, env=env), told=True)
    assert rate >= 0.95, [r["failure"] for r in results if not r["success"]]


def test_blind_approach_is_worse_than_the_oracle():
    env = FunctionalGraspEnv("mug")
    offsets = jitter_offsets(30, seed=2, env=env)
    told, _ = success_rate(env, offsets, told=True)
    blind, _ = success_rate(env, offsets, told=False)
    assert blind < told - 0.3


def test_label_command_works_for_a_user_added_object(tmp_path):
    assets = tmp_path / "assets"
    shutil.copytree(load_object("mug").path.parent.parent, assets)
    camera = load_object("camera")
    doorbell = {  # a bell push held like a camera: a user's own object, with the hint format's every key
        "name": "doorbell",
        "description": "A bell push on a hand-held block: a grip on the front right, a round button on top.",
        "mass": 0.5,
        "geoms": [
            {"name": "block", "type": "box", "size": [0.065, 0.035, 0.04], "pos": [0, 0, 0.04]},
            {"name": "grip", "type": "box", "size": [0.015, 0.01, 0.035], "pos": [0.045, 0.045, 0.04]},
            {"name": "button", "type": "cylinder", "size": [0.008, 0.003], "pos": [0.045, 0.015, 0.083]},
        ],
        "functional_part": ["button"],
        "grasp_hint": {
            "functional_finger": "ff",
            "grasp": "upright against the right end, fingers round the grip, thumb behind, index on the button",
            "contacts": {"mf": ["grip"], "rf": ["grip"], "lf": ["grip"], "th": ["block"]},
            "targets": {f: list(v) for f, v in camera.grasp_hint.targets.items()},
            "rotation": list(camera.grasp_hint.rotation), "palm_at": list(camera.grasp_hint.palm_at),
        },
    }
    (assets / "objects" / "doorbell.json").write_text(json.dumps(doorbell))
    env = {**os.environ, "FORCEGRASP_ASSETS": str(assets)}
    out = subprocess.run(
        [sys.executable, "-m", "forcegrasp.cli", "label", "doorbell"], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "functional finger touches button: True" in out.stdout
    saved = json.loads((assets / "labels" / "doorbell.json").read_text())
    assert saved["object"] == "doorbell" and saved["checks"]["functional_contact"] and saved["checks"]["holds"]
    assert saved["checks"]["pregrasp_clear_over_square"]
    assert (assets.parent / "docs" / "grasps" / "doorbell.png").is_file()
    # The new object is usable as an env straight away.
    check = subprocess.run(
        [sys.executable, "-c", "from forcegrasp.env import FunctionalGraspEnv as E; e=E('doorbell'); print(e.reset(seed=0)[0].shape)"],
        env=env, capture_output=True, text=True, timeout=120,
    )
    assert "(77,)" in check.stdout, check.stderr


def test_label_command_rejects_unknown_object():
    out = subprocess.run([sys.executable, "-m", "forcegrasp.cli", "label", "teapot"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "valid objects" in out.stderr


@pytest.mark.parametrize("name", OBJECTS)
def test_random_resets_never_start_inside_the_object(name):
    """Near the +x edge of the ±2 cm square the pre-grasp fingers would start up to 5.6 mm inside
    some objects (drill and spray bottle along a whole edge); random resets must redraw those."""
    env = FunctionalGraspEnv(name)
    for seed in range(200):
        _, info = env.reset(seed=seed)
        assert np.abs(info["offset"]).max() <= env.jitter
        assert hand_object_clearance(env.model, env.data, env.ix) > -1e-4, (seed, info["offset"])


def test_an_explicit_offset_inside_the_hand_is_refused_and_measured():
    env = FunctionalGraspEnv("mug")
    assert env.overlap((0.0, 0.0)) == 0.0 and env.is_clear((0.0, 0.0))
    # The labels' pre-grasps clear the whole ±2 cm square; further out, towards the hand, they do not.
    inside = next(o for o in ((x, y) for y in np.linspace(-0.02, -0.1, 17) for x in np.linspace(-0.06, 0.1, 17))
                  if env.overlap(o) > 0.004)
    assert not env.is_clear(inside)
    env.reset(seed=0)
    qpos = env.data.qpos.copy()
    env.overlap(inside)  # probes a scratch copy: the episode is untouched
    np.testing.assert_array_equal(env.data.qpos, qpos)
    with pytest.raises(ValueError, match=r"mm inside the pre-grasp hand"):
        env.reset(options={"offset": inside})
    np.testing.assert_array_equal(env.data.qpos, qpos)  # refused: the episode is as it was


def test_evaluation_placements_skip_offsets_a_clear_test_refuses():
    """Every label here is clear over the whole square, so exercise the filter with a stand-in
    test (a user's object may need it): refused offsets are redrawn, the stream stays prefix-stable."""
    clear = lambda offset: offset[0] < 0.01  # noqa: E731
    raw = placements(3, 100, 0.02, "rank")
    assert not all(clear(p.offset) for p in raw)
    kept = placements(3, 100, 0.02, "rank", clear=clear)
    assert all(clear(p.offset) for p in kept) and len(kept) == 100
    assert placements(3, 10, 0.02, "rank", clear=clear) == kept[:10]
    env = FunctionalGraspEnv("power_drill")
    assert all(env.is_clear(p.offset) for p in raw)  # the real test refuses none of them
