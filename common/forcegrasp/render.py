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


def object_camera(view, object_position) -> mujoco.MjvCamera:
    """The camera of an object's ``view`` (`forcegrasp.objects.View`, from its object file) with
    the object's origin at ``object_position`` (world, m): pictures and videos of that object."""
    target = np.asarray(object_position, dtype=float) + np.asarray(view.lookat, dtype=float)
    return look_at(target, view.distance, view.azimuth, view.elevation)


def render(renderer: mujoco.Renderer, d: mujoco.MjData, cam: mujoco.MjvCamera) -> np.ndarray:
    renderer.update_scene(d, cam)
    return renderer.render()


def save_png(path, image: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(image).save(path)


def grasp_picture(object_name: str, label=None, height: int = 300, width: int = 400) -> np.ndarray:
    """Pre-grasp and goal grasp side by side, each from the object's view (its file's ``view``, which
    shows the functional contact), from the approach side and from above."""
    from forcegrasp.labels import load_label
    from forcegrasp.objects import load_object
    from forcegrasp.scene import SceneIndex, build_model, resting_height

    label = label if label is not None else load_label(object_name)
    obj = load_object(object_name)
    m = build_model(obj)
    d = mujoco.MjData(m)
    ix = SceneIndex.of(m)
    renderer = make_renderer(m, height, width)
    rows = []
    for grasp in (label.pregrasp, label.goal):
        d.qpos[ix.all_qpos] = grasp.q
        d.qpos[ix.object_qpos + 2] = resting_height(m)
        d.qpos[ix.object_qpos + 3] = 1.0
        mujoco.mj_forward(m, d)
        views = [object_camera(obj.view, d.xpos[ix.object_body])]
        views += [look_at([0, 0, 0.09], 0.5, az, el) for az, el in ((135, -35), (270, -70))]
        rows.append(np.concatenate([render(renderer, d, cam) for cam in views], axis=1))
    renderer.close()
    return np.concatenate(rows, axis=0)
