"""``forcegrasp replay EPISODE.mcap``: render a logged episode offscreen to an image strip or a video.

The scene is rebuilt from the log's metadata (object and mass scale), then every logged step is
shown by setting the 30 hand joints (``/joint_states`` positions) and the object's free joint
(``object`` frame of ``/tf``) and running ``mj_forward`` (no simulation: the picture is the log).
The camera is the object's own (the ``view`` of its object file, looking at where the object
started), placed so the functional contact is in view.

Outputs, by the ``--out`` suffix (or ``--video``, which takes only the video formats):

- ``.png`` (default): a grid of ``--frames`` evenly spaced steps, each labelled;
- ``.gif``: every ``--stride``-th step (default 1; 320x240) as an animation;
- ``.mp4``: every ``--stride``-th step (default 1; 640x480) as an H.264 video (imageio-ffmpeg).

Videos play at ``--speed`` times the logged time (default 0.25: a grasp takes under a second).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


class ReplayError(ValueError):
    """The episode file cannot be replayed (not an episode log, unknown object...)."""


def load_scene(log):
    """(model, data, SceneIndex, ObjectSpec) for the logged object, or ReplayError."""
    import mujoco

    from forcegrasp.objects import ObjectFileError, load_object
    from forcegrasp.scene import SceneIndex, build_model

    meta = log.metadata
    if "object" not in meta:
        raise ReplayError(f"{log.path}: no forcegrasp.episode metadata: not a ForceGrasp episode log")
    try:
        obj = load_object(meta["object"])
    except ObjectFileError as exc:
        raise ReplayError(f"{log.path}: logged object cannot be rebuilt: {exc}") from None
    m = build_model(obj, float(meta.get("mass_scale", "1.0")))
    return m, mujoco.MjData(m), SceneIndex.of(m), obj


def render_frames(log, steps: list[int], height: int = 240, width: int = 320) -> list[np.ndarray]:
    """RGB frames of the given step indices (0 = the reset state), seen by the object's camera."""
    import mujoco

    from forcegrasp.render import make_renderer, object_camera, render

    m, d, ix, spec = load_scene(log)
    qpos, obj = log.qpos(), log.object_poses()
    if len(qpos) != len(obj):
        raise ReplayError(f"{log.path}: {len(qpos)} joint-state messages but {len(obj)} transforms")
    camera = object_camera(spec.view, obj[0, :3])  # fixed on where the object started
    renderer = make_renderer(m, height, width)
    frames = []
    try:
        for t in steps:
            d.qpos[ix.all_qpos] = qpos[t]
            d.qpos[ix.object_qpos: ix.object_qpos + 7] = obj[t]
            mujoco.mj_forward(m, d)
            frames.append(render(renderer, d, camera).copy())
    finally:
        renderer.close()
    return frames


def _label(frame: np.ndarray, text: str) -> np.ndarray:
    from PIL import Image, ImageDraw

    img = Image.fromarray(frame)
    draw = ImageDraw.Draw(img)
    draw.rectangle((0, 0, 8 + 7 * len(text), 16), fill=(0, 0, 0))
    draw.text((4, 2), text, fill=(255, 255, 255))
    return np.asarray(img)


def strip(frames: list[np.ndarray], labels: list[str], columns: int = 4) -> np.ndarray:
    frames = [_label(f, t) for f, t in zip(frames, labels)]
    h, w, c = frames[0].shape
    rows = -(-len(frames) // columns)
    grid = np.full((rows * h, min(columns, len(frames)) * w, c), 255, np.uint8)
    for i, f in enumerate(frames):
        r, col = divmod(i, columns)
        grid[r * h:(r + 1) * h, col * w:(col + 1) * w] = f
    return grid


def replay(path: str | Path, out: str | Path | None = None, frames: int = 8, stride: int | None = None,
           speed: float | None = None, height: int | None = None, width: int | None = None) -> Path:
    """Render ``path`` to ``out`` (see the module docstring); returns the file written."""
    from forcegrasp.mcap_log import read_episode
    from forcegrasp.render import save_png
    from forcegrasp.video import SPEED, VIDEO_SUFFIXES, VideoError, output_size, write_video

    path = Path(path)
    out = Path(out) if out is not None else path.with_suffix(".png")
    suffix = out.suffix.lower()
    if suffix not in (".png", *VIDEO_SUFFIXES):
        raise ReplayError(f"--out {out}: use a .png (image strip), .gif or .mp4 file name")
    try:
        width, height, stride = output_size(suffix, width, height, stride)
    except VideoError as exc:
        raise ReplayError(str(exc)) from None
    speed = SPEED if speed is None else speed
    if not np.isfinite(speed) or speed <= 0:
        raise ReplayError(f"--speed must be positive, got {speed!r}")
    try:
        episode = read_episode(path, topics=["/joint_states", "/tf", "/reward", "/outcome"])
    except FileNotFoundError:
        raise ReplayError(f"{path}: no such file") from None
    except Exception as exc:  # the mcap reader raises several types for non-MCAP input
        raise ReplayError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None
    if not episode.messages.get("/joint_states") or not episode.messages.get("/tf"):
        raise ReplayError(f"{path}: no /joint_states or /tf messages: not a ForceGrasp episode log")
    n = len(episode.messages["/joint_states"])
    rewards = episode.messages.get("/reward", [])
    fps = 1e9 / _step_ns(episode) * speed
    if suffix in VIDEO_SUFFIXES:
        steps = list(range(0, n, stride))
        if steps[-1] != n - 1:
            steps.append(n - 1)  # the final pose is always shown
        write_video(out, render_frames(episode, steps, height, width), fps / stride)
        return out
    steps = sorted({int(round(x)) for x in np.linspace(0, n - 1, max(1, min(frames, n)))})
    images = render_frames(episode, steps, height, width)
    labels = []
    for t in steps:
        ret = rewards[t]["return"] if t < len(rewards) else None
        labels.append(f"step {t}" + (f"  return {ret:.1f}" if ret is not None else ""))
    save_png(out, strip(images, labels))
    return out


def _step_ns(episode) -> int:
    times = episode.log_times.get("/joint_states", [])
    return max(1, times[1] - times[0]) if len(times) > 1 else 20_000_000


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp replay", description=__doc__.splitlines()[0],
                                     epilog="e.g. forcegrasp replay test-000.mcap --video grasp.gif")
    parser.add_argument("episode", help="an episode .mcap written by the evaluator or `forcegrasp eval --log-dir`")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--out", default=None, help="strip.png (default: next to the episode), anim.gif or video.mp4")
    where.add_argument("--video", default=None, metavar="OUT.{gif,mp4}", help="write the episode as a GIF or an MP4")
    parser.add_argument("--frames", type=int, default=8, help="frames in a PNG strip (default 8)")
    parser.add_argument("--stride", type=int, default=None,
                        help="render every n-th step in a video (default 1: every step)")
    parser.add_argument("--speed", type=float, default=None,
                        help="video playback speed against the logged time (default 0.25)")
    parser.add_argument("--width", type=int, default=None, help="frame width (default: 320; 640 in an MP4)")
    parser.add_argument("--height", type=int, default=None, help="frame height (default: 240; 480 in an MP4)")
    args = parser.parse_args(argv)
    try:
        if args.video is not None:
            from forcegrasp.video import VideoError, video_suffix

            try:
                video_suffix(args.video)
            except VideoError as exc:
                raise ReplayError(f"--video {exc}") from None
        out = replay(args.episode, args.video or args.out, frames=args.frames, stride=args.stride,
                     speed=args.speed, height=args.height, width=args.width)
    except ReplayError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
