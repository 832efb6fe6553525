"""Offscreen rendering on the CPU (EGL or OSMesa) for label pictures and episode replays."""

from __future__ import annotations

import mujoco
import numpy as np


def make_renderer(m: mujoco.MjModel, height: int = 360, width: int = 480) -> mujoco.Renderer:
    """A renderer with shadows and reflections off: ~5x faster on a software GL, still legible."""
    m.vis.global_.offwidth = max(m.vis.global_.offwidth, width)
    m.vis.global_.offheight = max(m.vis.global_.offheight, height)
    m.vis.quality.offsamples = 0
    renderer = mujoco.Renderer(m, height, width)
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
    return renderer


def look_at(lookat, distance: float = 0.45, azimuth: float = 135.0, elevation: float = -25.0) -> mujoco.MjvCamera:
    cam = mujoco.MjvCamera()
    cam.lookat[:] = lookat
    cam.distance, cam.azimuth, cam.elevation = distance, azimuth, elevation
    return cam


def render(renderer: mujoco.Renderer, d: mujoco.MjData, cam: mujoco.MjvCamera) -> np.ndarray:
    renderer.update_scene(d, cam)
    return renderer.render()


def save_png(path, image: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(image).save(path)
