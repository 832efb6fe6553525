"""``EpisodeLogger``: one evaluated episode to one ``.mcap`` file (temporary name until it ends)."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from forcegrasp.scene import ALL_JOINTS
from forcegrasp.mcap_log.messages import FIXED_LIMIT, FLOAT_WIDTH, INT_FMT, REWARD_FMT, SCENE_STAMP, SCHEMA_BYTES, STAMP_FMT, fixed_chars, frames_of, scene_json, templates, time_stamp
from forcegrasp.mcap_log.schemas import METADATA_NAME, PALM_FRAME, TOPIC_SCHEMAS, WORLD, dumps
from forcegrasp.mcap_log.writers import writer_class


class EpisodeLogger:
    """Writes one episode of a :class:`~forcegrasp.env.FunctionalGraspEnv` to an MCAP file.

    >>> log = EpisodeLogger(path, env, {"checkpoint_step": "4000"})
    >>> obs, info = env.reset(seed=seed, options={"offset": offset})
    >>> log.begin(seed, info)            # scene + step-0 state
    >>> log.step(action, reward, info)   # after every env.step()
    >>> log.end(ret, length, success, failure)   # closes the file under its final name

    Cost: ``step()`` only copies the step's numbers out of MuJoCo into preallocated arrays (a
    few contiguous gathers). ``end()`` turns the whole episode into messages at once — ``/tf``,
    ``/joint_states`` and ``/command`` as fixed-width JSON filled by numpy (6 decimals, see
    ``fixed_chars``), ``/reward`` by one %-format call at full precision — and writes them in
    time order. ``backend`` picks the MCAP writer: ``"sdk"`` (foxglove-sdk), ``"mcap"`` (pure
    Python) or ``"auto"`` (the SDK if installed).
    """

    def __init__(self, path: str | os.PathLike, env, metadata: dict[str, Any] | None = None,
                 chunk_size: int = 1 << 20, backend: str = "auto"):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = self.path.with_name(f".{self.path.name}.tmp")
        self.env = env
        self.m, self.d, self.ix = env.model, env.data, env.ix
        self.dt_ns = int(round(env.frame_skip * self.m.opt.timestep * 1e9))
        self.frames = frames_of(self.m, self.ix)
        self._joint_act = np.concatenate([self.ix.base_act, self.ix.hand_act])
        self._meta = {str(k): str(v) for k, v in (metadata or {}).items()}
        self._names = (*self.frames.names, PALM_FRAME)
        self._outcomes: list[tuple[bool, str | None]] = []
        self._allocate(env.max_steps + 1)
        self.writer = writer_class(backend)(self.tmp, chunk_size)
        self.channels = {topic: self.writer.channel(topic, schema, SCHEMA_BYTES[schema])
                         for topic, schema in TOPIC_SCHEMAS.items()}
        self.t0_ns = 0
        self.steps = 0
        self.closed = False

    def _allocate(self, n: int) -> None:
        """Per-step capture arrays for ``n`` steps (keeping what was captured so far)."""
        m = self.m
        # Whole MuJoCo arrays (plain copies are the cheapest capture); selection happens in end().
        shapes = {"xpos": (m.nbody, 3), "xquat": (m.nbody, 4), "palm": (7,), "qpos": (m.nq,),
                  "force": (m.nu,), "ctrl": (m.nu,), "action": (7,), "h": (), "rewards": (8,)}
        for name, shape in shapes.items():
            fresh = np.zeros((n, *shape))
            old = getattr(self, f"_{name}", None)
            if old is not None:
                fresh[:len(old)] = old
            setattr(self, f"_{name}", fresh)

    # ------------------------------------------------------------------ capture
    def _put(self, topic: str, t_ns: int, text: str) -> None:
        self.writer.write(self.channels[topic], t_ns, text.encode())

    def begin(self, seed: int, reset_info: dict, t0_ns: int | None = None) -> None:
        """Call right after ``env.reset()`` with its info: writes the metadata and the scene."""
        env = self.env
        self.t0_ns = time.time_ns() if t0_ns is None else int(t0_ns)
        self.seed, self.offset = int(seed), [float(o) for o in reset_info["offset"]]
        meta = {
            "object": env.object_spec.name, "mass_scale": repr(env.mass_scale),
            "force_feedback": str(env.force_feedback).lower(), "max_steps": str(env.max_steps),
            "frame_skip": str(env.frame_skip), "timestep": repr(float(self.m.opt.timestep)),
            "jitter": repr(env.jitter), "seed": str(self.seed),
            "offset_x": repr(self.offset[0]), "offset_y": repr(self.offset[1]),
            "joints": ",".join(ALL_JOINTS), "start_time_ns": str(self.t0_ns), **self._meta,
        }
        self.writer.metadata(METADATA_NAME, meta)
        self._put("/scene", self.t0_ns, scene_json(self.m, self.ix, env.object_spec.name).replace(
            SCENE_STAMP, dumps(time_stamp(self.t0_ns))))
        # Step 0 is the reset state: no reward yet, its terms as the env would compute them.
        h = float(reset_info["h"])
        palm_rel = self.d.site_xpos[self.ix.palm_site] - self.d.xpos[self.ix.object_body]
        palm_error = float(np.linalg.norm(palm_rel - env.label.goal_palm))
        self._capture(0, np.zeros(7), 0.0, {
            "r_a": -abs(1.0 - h), "r_b": -palm_error, "r_c": 0.0, "h": h, "object_displacement": 0.0,
            "palm_error": palm_error, "success": False, "failure": None})

    def step(self, action, reward: float, info: dict) -> None:
        """Call after each ``env.step()`` with its action, reward and info."""
        self.steps += 1
        self._capture(self.steps, action, reward, info)

    def _capture(self, k: int, action, reward: float, info: dict) -> None:
        if k >= len(self._xpos):  # more steps than max_steps (never in the env's own loop): grow
            self._allocate(2 * len(self._xpos))
        d, palm = self.d, self._palm[k]
        self._xpos[k] = d.xpos
        self._xquat[k] = d.xquat
        palm[:3] = d.site_xpos[self.ix.palm_site]
        mujoco.mju_mat2Quat(palm[3:], d.site_xmat[self.ix.palm_site])
        self._qpos[k] = d.qpos
        self._force[k] = d.actuator_force
        self._ctrl[k] = d.ctrl
        self._action[k] = action
        self._h[k] = self.env.h_command
        self._rewards[k] = (reward, info["r_a"], info["r_b"], info["r_c"], info["h"], info["object_displacement"],
                            info["palm_error"], self.env.episode_return)
        self._outcomes.append((bool(info["success"]), info["failure"]))

    # ------------------------------------------------------------------ writing
    def _step_values(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per step, the numbers of /tf, /joint_states and /command, in their slot order."""
        b, xyzw = self.frames.bodies, [1, 2, 3, 0]  # MuJoCo quaternions are w,x,y,z
        pos = np.concatenate([self._xpos[:n, b], self._palm[:n, None, :3]], axis=1)
        quat = np.concatenate([self._xquat[:n, b], self._palm[:n, None, 3:]], axis=1)[:, :, xyzw]
        tf = np.concatenate([pos, quat], axis=2)
        joints = np.stack([self._qpos[:n, self.ix.all_qpos], self._force[:n, self._joint_act]], axis=2)
        command = np.concatenate([self._action[:n], self._ctrl[:n, self._joint_act], self._h[:n, None]], axis=1)
        return tf.reshape(n, -1), joints.reshape(n, -1), command

    def _flush(self) -> None:
        """All captured steps as messages, in time order."""
        n = self.steps + 1
        times = [self.t0_ns + k * self.dt_ns for k in range(n)]
        stamps = np.frombuffer(b"".join(STAMP_FMT % divmod(t, 1_000_000_000) for t in times), np.uint8).reshape(n, -1)
        ints = np.frombuffer(b"".join(INT_FMT % k for k in range(n)), np.uint8).reshape(n, -1)
        blobs, slow = [], np.zeros(n, bool)
        for template, values in zip(templates(self._names), self._step_values(n)):
            ok = np.abs(values) < FIXED_LIMIT  # False for NaN too
            slow |= ~ok.all(axis=1)
            chars = fixed_chars(np.where(ok, values, 0.0).ravel()).reshape(n, -1, FLOAT_WIDTH)
            blobs.append(template.fill(chars, stamps, ints))
        tf, joints, command = blobs
        fields = []
        for k, row in enumerate(self._rewards[:n].tolist()):
            success, failure = self._outcomes[k]
            fields += [*divmod(times[k], 1_000_000_000), k, *(x if math.isfinite(x) else "null" for x in row),
                       "true" if success else "false", "null" if failure is None else dumps(str(failure))]
        rewards = ("\n".join([REWARD_FMT] * n) % tuple(fields)).encode().split(b"\n")
        write, ch = self.writer.write, self.channels
        for k in range(n):
            t = times[k]
            if slow[k]:
                self._put_slow(k, t)
            else:
                write(ch["/tf"], t, tf[k].tobytes())
                write(ch["/joint_states"], t, joints[k].tobytes())
                write(ch["/command"], t, command[k].tobytes())
            write(ch["/reward"], t, rewards[k])

    def _put_slow(self, k: int, t_ns: int) -> None:
        """A step with out-of-range or non-finite numbers (a diverged simulation): plain json,
        NaN/inf as null."""
        stamp = time_stamp(t_ns)
        tf, joints, command = ([_num(x) for x in v[k]] for v in self._step_values(k + 1))
        self._put("/tf", t_ns, dumps({"transforms": [
            {"timestamp": stamp, "parent_frame_id": WORLD, "child_frame_id": name,
             "translation": dict(zip("xyz", tf[7 * f:7 * f + 3])), "rotation": dict(zip("xyzw", tf[7 * f + 3:7 * f + 7]))}
            for f, name in enumerate(self._names)]}))
        self._put("/joint_states", t_ns, dumps({"timestamp": stamp, "joints": [
            {"name": name, "position": joints[2 * j], "effort": joints[2 * j + 1]} for j, name in enumerate(ALL_JOINTS)]}))
        self._put("/command", t_ns, dumps({"timestamp": stamp, "step": k, "action": command[:7],
                                            "targets": command[7:-1], "h_command": command[-1]}))

    def end(self, episode_return: float, length: int, success: bool, failure: str | None) -> Path:
        """Write every step, the outcome, finish the file and give it its final name."""
        self._flush()
        t_ns = self.t0_ns + self.steps * self.dt_ns
        self._put("/outcome", t_ns, dumps({
            "timestamp": time_stamp(t_ns), "return": _num(episode_return), "length": int(length),
            "success": bool(success), "failure": failure, "seed": self.seed, "offset": self.offset}))
        self.writer.close()
        os.replace(self.tmp, self.path)
        self.closed = True
        return self.path

    def abort(self) -> None:
        """Drop an unfinished episode (e.g. the service is stopping): no file is left behind."""
        if self.closed:
            return
        self.closed = True
        try:
            self.writer.discard()
        finally:
            try:
                os.unlink(self.tmp)
            except FileNotFoundError:
                pass


def _num(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None
