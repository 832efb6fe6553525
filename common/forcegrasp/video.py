"""Episode videos: offscreen-rendered frames written as an animated GIF or an MP4.

One writer serves every command that makes a video (``forcegrasp replay EPISODE.mcap --video``,
``forcegrasp eval POLICY --video``, the report's grasp GIFs):

- ``.gif``: Pillow, one 255-colour palette shared by all frames (no dithering), so the still
  background is identical from frame to frame and each frame stores only what moved; a
  repeated frame is merged into the one before (its time added to that frame's);
- ``.mp4``: H.264 through imageio's ffmpeg plugin and the ffmpeg binary of the ``imageio-ffmpeg``
  wheel (a declared dependency: no system ffmpeg needed).

Videos play at ``SPEED`` (a quarter of real time: a grasp takes half a second to a second) and
hold the last frame for ``HOLD_SECONDS`` so the final grasp can be seen before the loop restarts.
Every frame of an episode is taken by the object's own camera (the ``view`` of its object file,
looking at where the object started), so the functional contact is in view.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

VIDEO_SUFFIXES = (".gif", ".mp4")
#: frame size and step stride by format when the caller gives none: GIFs small (they go in docs)
DEFAULTS = {".gif": {"width": 320, "height": 240, "stride": 1}, ".mp4": {"width": 640, "height": 480, "stride": 1}}
#: playback speed against simulated time: a grasp takes 0.5 to 1 s (25 to 50 steps), too quick to follow
SPEED = 0.25
HOLD_SECONDS = 1.0


class VideoError(ValueError):
    """A video cannot be written (unsupported file name, no frames)."""


@dataclass(frozen=True)
class VideoInfo:
    path: Path
    frames: int  # frames in the file (GIF: repeats merged; MP4: the held last frame counted)
    width: int
    height: int
    fps: float  # frames per second of the rendered steps (playback)


def video_suffix(path) -> str:
    """``.gif`` or ``.mp4`` (case-insensitive), else VideoError naming the path."""
    suffix = Path(path).suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise VideoError(f"{path}: a video must be a .gif or .mp4 file, got {suffix or 'no suffix'!r}")
    return suffix


def write_video(path, frames: list[np.ndarray], fps: float, hold: float = HOLD_SECONDS) -> VideoInfo:
    """Write RGB ``frames`` (uint8, H x W x 3, all one size) shown at ``fps`` to ``path``."""
    path = Path(path)
    suffix = video_suffix(path)
    if not frames:
        raise VideoError(f"{path}: no frames to write")
    if not np.isfinite(fps) or fps <= 0:
        raise VideoError(f"{path}: frames per second must be positive, got {fps!r}")
    frames = [np.ascontiguousarray(f[..., :3], dtype=np.uint8) for f in frames]
    h, w = frames[0].shape[:2]
    if any(f.shape[:2] != (h, w) for f in frames):
        raise VideoError(f"{path}: frames differ in size")
    path.parent.mkdir(parents=True, exist_ok=True)
    count = (_write_gif if suffix == ".gif" else _write_mp4)(path, frames, float(fps), max(0.0, float(hold)))
    return VideoInfo(path, count, w, h, float(fps))


def _write_gif(path: Path, frames: list[np.ndarray], fps: float, hold: float) -> int:
    from PIL import Image

    # A palette from a few frames spread over the episode, used for every frame without dithering;
    # maximum coverage keeps small rare colours (a red shutter button) that median cut merges away.
    sample = [frames[i] for i in np.linspace(0, len(frames) - 1, min(len(frames), 8)).round().astype(int)]
    palette = Image.fromarray(np.concatenate(sample, axis=0)).quantize(colors=255, method=Image.Quantize.MAXCOVERAGE)
    step_ms = 1000.0 / fps
    images, durations, clock = [], [], 0.0
    for i, frame in enumerate(frames):
        # GIF delays count in 10 ms: round on the running clock so the total time stays right.
        start, clock = round(clock / 10) * 10, clock + step_ms + (1000.0 * hold if i == len(frames) - 1 else 0.0)
        image = Image.fromarray(frame).quantize(palette=palette, dither=Image.Dither.NONE)
        if images and image.tobytes() == images[-1].tobytes():
            durations[-1] += round(clock / 10) * 10 - start
            continue
        images.append(image)
        durations.append(round(clock / 10) * 10 - start)
    durations = [max(20, d) for d in durations]  # viewers play shorter delays slowly
    images[0].save(path, save_all=True, append_images=images[1:], duration=durations, loop=0, disposal=1)
    return len(images)


def _write_mp4(path: Path, frames: list[np.ndarray], fps: float, hold: float) -> int:
    import imageio.v2 as imageio

    extra = int(round(hold * fps))
    # macro_block_size 2: H.264 in yuv420p needs even sizes; an odd one is padded by imageio
    with imageio.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264", pixelformat="yuv420p",
                            macro_block_size=2, ffmpeg_log_level="error") as writer:
        for frame in frames + [frames[-1]] * extra:
            writer.append_data(frame)
    return len(frames) + extra


def output_size(suffix: str, width: int | None, height: int | None, stride: int | None) -> tuple[int, int, int]:
    """(width, height, stride): the caller's, or the format's defaults."""
    d = DEFAULTS.get(suffix, DEFAULTS[".gif"])  # a PNG strip: 320x240 tiles
    width, height, stride = width or d["width"], height or d["height"], stride or d["stride"]
    if width < 16 or height < 16 or stride < 1:
        raise VideoError(f"video size {width}x{height} (at least 16x16) or stride {stride} (at least 1) out of range")
    return int(width), int(height), int(stride)


# ------------------------------------------------------------------------- episodes of an env
class FrameRecorder:
    """Takes a picture of ``env`` at the reset and every ``stride``-th step (and the last one) with
    the object's camera. It has the episode-logger methods `forcegrasp.evaluation.run_episode`
    calls, so a recorded episode is exactly the one ``forcegrasp eval`` scores."""

    def __init__(self, env, width: int, height: int, stride: int = 1):
        from forcegrasp.render import make_renderer

        self.env, self.stride = env, max(1, int(stride))
        self.renderer = make_renderer(env.model, height, width)
        self.frames: list[np.ndarray] = []
        self._camera = None
        self._steps = 0

    def _shot(self) -> None:
        from forcegrasp.render import render

        self.frames.append(render(self.renderer, self.env.data, self._camera).copy())

    def begin(self, seed, info) -> None:
        from forcegrasp.render import object_camera

        self._camera = object_camera(self.env.object_spec.view, self.env.object_position())
        self.frames, self._steps = [], 0
        self._shot()

    def step(self, action, reward, info) -> None:
        self._steps += 1
        if self._steps % self.stride == 0:
            self._shot()

    def end(self, ret, length, success, failure) -> None:
        if self._steps % self.stride:
            self._shot()  # the final pose is always shown
        self.close()

    def abort(self) -> None:
        self.close()

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None


def step_fps(env) -> float:
    """Env steps per simulated second (50 at the default 2 ms x 10 substeps)."""
    return 1.0 / (float(env.model.opt.timestep) * int(env.frame_skip))


def record_episode(env, policy, placement, width: int, height: int, stride: int = 1):
    """(frames, EpisodeResult) of one deterministic episode of ``policy`` from ``placement``."""
    from forcegrasp.evaluation import run_episode

    recorder = FrameRecorder(env, width, height, stride)
    result = run_episode(env, policy, placement, logger=recorder)
    return recorder.frames, result


def episode_video(env, policy, placement, out, *, width: int | None = None, height: int | None = None,
                  stride: int | None = None, speed: float = SPEED, hold: float = HOLD_SECONDS):
    """Render one episode to ``out`` (.gif or .mp4): (VideoInfo, EpisodeResult)."""
    suffix = video_suffix(out)
    width, height, stride = output_size(suffix, width, height, stride)
    frames, result = record_episode(env, policy, placement, width, height, stride)
    return write_video(out, frames, step_fps(env) * speed / stride, hold), result
