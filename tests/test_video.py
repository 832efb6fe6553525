"""Episode videos (forcegrasp.video): GIF and MP4 from the offscreen renderer, read back with imageio;
``forcegrasp eval POLICY --video`` and ``forcegrasp replay EPISODE --video``; the objects' ``view``."""

import json
import re

import imageio.v2 as imageio
import numpy as np
import pytest

from forcegrasp.objects import ObjectFileError, View, load_object, load_object_file, parse_object
from forcegrasp.video import HOLD_SECONDS, VideoError, record_episode, step_fps, write_video


def read_back(path):
    frames = [np.asarray(f) for f in imageio.mimread(path, memtest=False)]
    return len(frames), {f.shape[:2] for f in frames}, frames


@pytest.fixture(scope="module")
def short_episode():
    """Six steps of the shipped mug policy (force feedback, seed 0) on the first held-out placement,
    rendered at 96x64."""
    from forcegrasp import ASSETS_DIR
    from forcegrasp.env import FunctionalGraspEnv
    from forcegrasp.evaluation import placements
    from forcegrasp.policy import Policy

    policy = Policy.load(ASSETS_DIR / "policies" / "mug-ff-s0.safetensors")
    env = FunctionalGraspEnv.for_policy(policy.metadata, max_steps=6)
    place = placements(0, 1, env.jitter, "test", clear=env.is_clear)[0]
    frames, result = record_episode(env, policy, place, width=96, height=64, stride=1)
    env.close()
    return frames, result, step_fps(env)


def test_a_short_episode_becomes_a_gif_and_an_mp4(short_episode, tmp_path):
    frames, result, fps = short_episode
    assert result.length == 6 and len(frames) == 7  # the reset and every step
    assert all(f.shape == (64, 96, 3) and f.dtype == np.uint8 for f in frames)
    assert frames[0].std() > 10 and not np.array_equal(frames[0], frames[-1])  # a scene, and it moves
    assert all(not np.array_equal(a, b) for a, b in zip(frames, frames[1:]))  # so no GIF frame is merged

    gif = write_video(tmp_path / "episode.gif", frames, fps / 4)
    n, sizes, back = read_back(gif.path)
    assert (n, sizes) == (7, {(64, 96)}) and gif.frames == 7 and (gif.width, gif.height) == (96, 64)
    # one shared palette, no dithering: every pixel within a few levels of the render
    assert max(np.abs(b[..., :3].astype(int) - f).max() for b, f in zip(back, frames)) < 40
    assert np.abs(back[-1][..., :3].astype(int) - frames[-1]).mean() < 4

    mp4 = write_video(tmp_path / "episode.mp4", frames, fps / 4)
    n, sizes, back = read_back(mp4.path)
    held = round(HOLD_SECONDS * fps / 4)  # the last frame is held a second
    assert (n, sizes) == (7 + held, {(64, 96)}) and mp4.frames == n
    assert np.abs(back[0].astype(int) - frames[0]).mean() < 12  # H.264 is lossy, not wrong


def test_video_errors_are_clear(short_episode, tmp_path):
    frames, _, _ = short_episode
    with pytest.raises(VideoError, match=r"clip\.webm: a video must be a \.gif or \.mp4 file"):
        write_video(tmp_path / "clip.webm", frames, 10)
    with pytest.raises(VideoError, match="no frames"):
        write_video(tmp_path / "clip.gif", [], 10)
    with pytest.raises(VideoError, match="differ in size"):
        write_video(tmp_path / "clip.gif", [frames[0], frames[1][:32]], 10)
    assert not list(tmp_path.iterdir())


def test_eval_video_renders_the_first_held_out_placement(tmp_path, capsys):
    """`forcegrasp eval mug-ff-s0 --video out.gif`: one command, no MCAP."""
    from forcegrasp.cli import main

    out = tmp_path / "grasp.gif"
    assert main(["eval", "mug-ff-s0", "--video", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "test placement 0" in printed and f"wrote {out}" in printed
    steps = int(printed.split(" steps: wrote")[0].rsplit(" ", 1)[1])
    n, sizes, frames = read_back(out)
    assert sizes == {(240, 320)} and 2 <= n <= steps + 1  # reset + every step, repeats merged
    assert frames[0].std() > 10

    with pytest.raises(SystemExit) as exc:  # a file name that is no video: refused before any work
        main(["eval", "mug-ff-s0", "--video", str(tmp_path / "grasp.avi")])
    assert exc.value.code == 2 and "use a .gif or .mp4 file name, or a directory" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["eval", "mug-ff-s0", "--video", str(out), "--sweep", "mass_scale=1,2"])
    assert "--video renders episodes and scores none" in capsys.readouterr().err


def test_eval_video_directory_and_replay_video(tmp_path, capsys):
    """`--video DIR` writes one video per placement; `forcegrasp replay EPISODE.mcap --video` renders a log."""
    from forcegrasp.cli import main

    assert main(["eval", "camera-ff-s0", "--video", str(tmp_path / "videos"), "--video-count", "2",
                 "--video-format", "mp4"]) == 0
    assert sorted(p.name for p in (tmp_path / "videos").iterdir()) == ["test-000.mp4", "test-001.mp4"]
    n, sizes, _ = read_back(tmp_path / "videos" / "test-001.mp4")
    assert sizes == {(480, 640)} and n > 13  # at least the held second

    assert main(["eval", "camera-ff-s0", "--episodes", "1", "--log-dir", str(tmp_path / "logs")]) == 0
    (episode,) = (tmp_path / "logs" / "as-given").glob("*.mcap")
    capsys.readouterr()
    gif, mp4 = tmp_path / "replay.gif", tmp_path / "replay.mp4"
    assert main(["replay", str(episode), "--video", str(gif), "--width", "128", "--height", "96"]) == 0
    assert main(["replay", str(episode), "--video", str(mp4), "--stride", "3", "--width", "128", "--height", "96"]) == 0
    from forcegrasp.mcap_log import read_episode

    steps = len(read_episode(episode, topics=["/joint_states"]).messages["/joint_states"])
    n, sizes, _ = read_back(gif)
    assert sizes == {(96, 128)} and 2 <= n <= steps
    n, sizes, _ = read_back(mp4)
    logged = len(range(0, steps, 3)) + ((steps - 1) % 3 != 0)  # every third step and the last
    assert sizes == {(96, 128)} and n == logged + round(HOLD_SECONDS * 50 * 0.25 / 3)
    assert main(["replay", str(episode), "--video", str(tmp_path / "strip.png")]) == 1
    assert "a video must be a .gif or .mp4 file" in capsys.readouterr().err


# ------------------------------------------------------------------------------ the objects' view
def test_every_object_has_a_view_of_its_own():
    views = {name: load_object(name).view for name in ("mug", "camera", "power_drill", "spray_bottle")}
    assert all(v != View() for v in views.values()) and len(set(views.values())) == 4
    raw = json.loads(load_object("mug").path.read_text())
    del raw["view"]
    assert parse_object(raw).view == View()  # optional: the default camera


@pytest.mark.parametrize("view, field", [
    ({"azimuth": "north"}, "view.azimuth"),
    ({"elevation": -120}, "view.elevation"),
    ({"distance": 0}, "view.distance"),
    ({"distance": True}, "view.distance"),
    ({"lookat": [0, 0]}, "view.lookat"),
    ({"lookat": [0, 0, 3]}, "view.lookat"),
    ({"elevation": float("nan")}, "view.elevation"),
    ({"zoom": 2}, "unknown keys"),
    ([200, -25, 0.5], "'view' must be a map"),
])
def test_a_bad_view_is_a_clear_error(tmp_path, view, field):
    raw = json.loads(load_object("mug").path.read_text())
    raw["view"] = view
    path = tmp_path / "mug.json"
    path.write_text(json.dumps(raw))
    with pytest.raises(ObjectFileError, match=re.escape(f"{path}: ") + ".*" + re.escape(field)):
        load_object_file(path)


def test_the_report_shows_a_grasp_gif_per_object(tmp_path):
    """`forcegrasp report` renders the first successful held-out grasp as results/grasp-<object>.gif and
    its page shows the GIFs (docs/results.md is that page)."""
    from forcegrasp.cli.report import grasp_video, write_page
    from forcegrasp.report import shipped_policies

    shipped = next(s for s in shipped_policies() if s.obj == "power_drill" and s.force_feedback)
    gif = grasp_video(shipped, tmp_path / "results" / "grasp-power_drill.gif")
    n, sizes, _ = read_back(gif)
    assert sizes == {(240, 320)} and n > 5 and gif.stat().st_size < 500_000
    page = write_page([], {}, {"grasp-power_drill": gif}, "quick", 1.0, tmp_path).read_text()
    assert "![grasp-power_drill](results/grasp-power_drill.gif)" in page


def test_grasp_picture_renders_with_the_objects_view():
    from forcegrasp.render import grasp_picture

    picture = grasp_picture("camera", height=60, width=80)
    assert picture.shape == (120, 240, 3) and picture.std() > 10
