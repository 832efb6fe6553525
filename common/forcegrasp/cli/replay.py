"""``forcegrasp replay EPISODE.mcap``: render a logged episode offscreen to an image strip or a video.

The scene is rebuilt from the log's metadata (object and mass scale), then every logged step is
shown by setting the 30 hand joints (``/joint_states`` positions) and the object's free joint
(``object`` frame of ``/tf``) and running ``mj_forward`` (no simulation: the picture is the log).

Outputs, by the ``--out`` suffix:

- ``.png`` (default, always possible): a grid of ``--frames`` evenly spaced steps, each labelled;
- ``.gif``: every ``--stride``-th step as an animation (Pillow, always possible);
- ``.mp4``: a video, when imageio with an ffmpeg backend is installed; otherwise a PNG strip is
  written next to it and the command says so.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np


class ReplayError(ValueError):
    """The episode file cannot be replayed (not an episode log, unknown object...)."""


def _ffmpeg_writer_available() -> bool:
    try:
        import imageio.v2  # noqa: F401
    except ImportError:
        return False
    try:
        import imageio_ffmpeg  # noqa: F401

        return True
    except ImportError:
        return shutil.which("ffmpeg") is not None


def load_scene(log):
    """(model, data, SceneIndex) for the logged object, or ReplayError."""
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
    return m, mujoco.MjData(m), SceneIndex.of(m)


def render_frames(log, steps: list[int], height: int = 240, width: int = 320) -> list[np.ndarray]:
    """RGB frames of the given step indices (0 = the reset state)."""
    import mujoco

    from forcegrasp.render import look_at, make_renderer, render

    m, d, ix = load_scene(log)
    qpos, obj = log.qpos(), log.object_poses()
    if len(qpos) != len(obj):
        raise ReplayError(f"{log.path}: {len(qpos)} joint-state messages but {len(obj)} transforms")
    renderer = make_renderer(m, height, width)
    frames = []
    try:
        for t in steps:
            d.qpos[ix.all_qpos] = qpos[t]
            d.qpos[ix.object_qpos: ix.object_qpos + 7] = obj[t]
            mujoco.mj_forward(m, d)
            target = obj[t, :3] + np.array([0.0, 0.0, 0.08])
            frames.append(render(renderer, d, look_at(target, 0.55, 200.0, -25.0)).copy())
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


def replay(path: str | Path, out: str | Path | None = None, frames: int = 8, stride: int = 1, fps: int | None = None,
           height: int = 240, width: int = 320, log=print) -> Path:
    """Render ``path`` to ``out`` (see the module docstring); returns the file written."""
    from forcegrasp.mcap_log import read_episode
    from forcegrasp.render import save_png

    path = Path(path)
    try:
        episode = read_episode(path, topics=["/joint_states", "/tf", "/reward", "/outcome"])
    except FileNotFoundError:
        raise ReplayError(f"{path}: no such file") from None
    except Exception as exc:  # the mcap reader raises several types for non-MCAP input
        raise ReplayError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None
    if not episode.messages.get("/joint_states") or not episode.messages.get("/tf"):
        raise ReplayError(f"{path}: no /joint_states or /tf messages: not a ForceGrasp episode log")
    out = Path(out) if out is not None else path.with_suffix(".png")
    n = len(episode.messages["/joint_states"])
    rewards = episode.messages.get("/reward", [])
    fps = fps or max(1, round(1e9 / _step_ns(episode)))
    suffix = out.suffix.lower()
    if suffix == ".mp4" and not _ffmpeg_writer_available():
        log("no ffmpeg backend for imageio here (pip install imageio-ffmpeg): writing an image strip instead")
        out, suffix = out.with_suffix(".png"), ".png"
    if suffix in (".mp4", ".gif"):
        steps = list(range(0, n, max(1, stride)))
        images = render_frames(episode, steps, height, width)
        if suffix == ".gif":
            from PIL import Image

            pil = [Image.fromarray(f) for f in images]
            pil[0].save(out, save_all=True, append_images=pil[1:], duration=int(1000 * max(1, stride) / fps), loop=0)
        else:
            import imageio.v2 as imageio

            imageio.mimwrite(out, images, fps=fps / max(1, stride))
        return out
    if suffix != ".png":
        raise ReplayError(f"--out {out}: use a .png (image strip), .gif or .mp4 file name")
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
    parser = argparse.ArgumentParser(prog="forcegrasp replay", description=__doc__.splitlines()[0])
    parser.add_argument("episode", help="an episode .mcap written by the evaluator")
    parser.add_argument("--out", default=None, help="strip.png (default: next to the episode), anim.gif or video.mp4")
    parser.add_argument("--frames", type=int, default=8, help="frames in a PNG strip (default 8)")
    parser.add_argument("--stride", type=int, default=1, help="render every n-th step in a video or GIF")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    args = parser.parse_args(argv)
    try:
        out = replay(args.episode, args.out, frames=args.frames, stride=args.stride, height=args.height,
                     width=args.width)
    except ReplayError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
