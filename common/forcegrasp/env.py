"""FunctionalGrasp: move the ADROIT hand from a pre-grasp to a goal functional grasp by touch.

The paper's MDP (sections III-V of ``functional-grasp-force-feedback.tex``), one env per file.

Observation (Table I; 77 float32, 53 without force feedback; [with commanded proprioception]):

    ====================  ====  =================================================================
    joint_torques F        24   actuator force of each hand joint servo (N·m): what a joint
                                torque sensor reads; optional Gaussian noise N(0, sigma) N·m
    joint_angles J         24   hand joint angles (rad) [joint_targets J(h_cmd) = h_cmd (Jg - J0) + J0]
    hand_pose              6    the base's driving joints: 3 slides (m) and 3 hinges (rad) [base_command]
    h                      1    observed progress 1 - 0.5 max_i |j_i - j_i^g| / range_i [h_command]
    base_targets           6    the base servo targets the policy has commanded
    prev_hand_pose         6    hand_pose at the previous step [prev_base_command]
    prev_h                 1    h at the previous step [prev_h_command]
    goal_pose (Tg, Rg)     6    goal base joint values (object at its nominal pose)
    goal_palm              3    goal palm position in the world (object at its nominal pose)
    ====================  ====  =================================================================

Nothing about the object's pose, geometry or mass is observed: the jitter is only felt. But the joints
are position servos (torque = kp (target - angle) - kv velocity), so the measured angles, pose and h
show a contact too. ``proprioception="commanded"`` (a lever outside Table I, never the default) puts
what the policy commanded in their places, under their own names (so that policy files record the
mode): the hand's ctrl J(h_cmd), the base targets (base_command repeats base_targets) and h_cmd, now
and one step before. Commanded without force feedback, nothing observed depends on the object;
rewards, success and ``info["h"]`` stay measured. With ``torque_history`` k > 0 (a recipe lever
outside Table I, never the default) a ``torque_history`` segment of 24 k follows ``joint_torques``:
the torques observed at the k previous steps, newest first (at reset, copies of the first reading).
With ``torque_filter`` a < 1 (a lever outside Table I, reported apart) the torques observed are an
exponential moving average of the readings, noise included: a reading + (1 - a) the last observed.

Action (7, in [-1, 1]): increments of the 6 base targets (scaled by ``max_translation_step`` m
and ``max_rotation_step`` rad) and of the commanded h (by ``max_h_step``); the 24 hand joints
follow J = h (Jg - J0) + J0. A NaN or out-of-range action raises ``ValueError``.

Reward r = w + wa ra + wb rb + wc rc with ra = -|1 - h|, rb = -||p - p_g|| (palm relative to the
*current* object position vs. its goal), rc = -||T_c - T~|| (object displacement from its
jittered start). Success (|rc| < 0.01, |ra| < 0.05, |rb| < 0.01) adds 1000 + 1.5 (200 - step)
and terminates; moving the object beyond ``object_tolerance`` or the palm beyond
``palm_tolerance`` fails at once; a return below ``abort_return`` aborts; ``max_steps`` truncates.
Failures and aborts are terminal states (``terminated=True``); only the step limit truncates.
"""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np

from forcegrasp.labels import GraspLabel, load_label
from forcegrasp.objects import load_object
from forcegrasp.reward import Outcome, RewardWeights, evaluate_state, observed_h  # noqa: F401  (part of this module's API)
from forcegrasp.sampling import draw, draw_clear_offset, span as checked_range
from forcegrasp.scene import SceneIndex, block_view, build_model, resting_height, slide_axes
from forcegrasp.task import (  # noqa: F401  (the layouts are part of this module's documented API)
    ACTION_LAYOUT, ACTION_STEPS, COMMANDED_SLOTS, DOMAIN, OBS_LAYOUT, PRIV_DIM, PRIVILEGED_LAYOUT, action_scale,
    action_steps_of, observation_layout, proprioception_of, torque_history_of,
)

# A jittered placement is usable when the pre-grasp hand does not start inside the object (deeper
# than this, in m); near some edges of the ±2 cm square it would. Random resets redraw such offsets.
OVERLAP_TOLERANCE = 1e-4
_ACTION_LIMIT = 1.0 + 1e-6  # actions are in [-1, 1]; this much float slack is tolerated


class FunctionalGraspEnv(gym.Env):
    """One object, one pre-grasp/goal pair, object x-y jittered by up to ``jitter`` m per reset."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(
        self,
        object_name: str = "mug",
        *,
        force_feedback: bool = True,
        mass_scale: float = 5.0,
        jitter: float = 0.02,
        torque_noise_std: float = 0.0,
        frame_skip: int = 10,
        max_steps: int = 200,
        object_tolerance: float = 0.01,
        palm_tolerance: float = 0.1,
        abort_return: float = -50.0,
        success_tolerances: tuple[float, float, float] = (0.01, 0.05, 0.01),
        reward_weights: RewardWeights = RewardWeights(),
        max_translation_step: float = ACTION_STEPS[0],
        max_rotation_step: float = ACTION_STEPS[1],
        max_h_step: float = ACTION_STEPS[2],
        torque_history: int = 0,
        torque_filter: float = 1.0,
        proprioception: str = "measured",
        mass_scale_range: tuple[float, float] | None = None,
        torque_noise_range: tuple[float, float] | None = None,
        jitter_range: tuple[float, float] | None = None,
        label: GraspLabel | None = None,
        render_mode: str | None = None,
    ):
        for name, value in (("mass_scale", mass_scale), ("frame_skip", frame_skip), ("max_steps", max_steps)):
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be positive, got {value!r}")
        if not (np.isfinite(jitter) and jitter >= 0) or not (np.isfinite(torque_noise_std) and torque_noise_std >= 0):
            raise ValueError(f"jitter and torque_noise_std must be >= 0, got {jitter!r}, {torque_noise_std!r}")
        self.mass_scale_range = checked_range("mass_scale_range", mass_scale_range, positive=True)
        self.torque_noise_range = checked_range("torque_noise_range", torque_noise_range, positive=False)
        self.jitter_range = checked_range("jitter_range", jitter_range, positive=False)
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None")
        self.object_spec = load_object(object_name)
        self.label = label if label is not None else load_label(object_name)
        self.force_feedback, self.torque_history = bool(force_feedback), int(torque_history)
        if not 0.0 < torque_filter <= 1.0:
            raise ValueError(f"torque_filter must be in (0, 1], got {torque_filter!r}")
        self.torque_filter = float(torque_filter)
        self.proprioception, self._commanded = proprioception, proprioception == "commanded"
        self.mass_scale, self.jitter, self.torque_noise_std = float(mass_scale), float(jitter), float(torque_noise_std)
        self.frame_skip, self.max_steps = int(frame_skip), int(max_steps)
        self.object_tolerance, self.palm_tolerance = float(object_tolerance), float(palm_tolerance)
        self.abort_return, self.success_tolerances = float(abort_return), tuple(success_tolerances)
        self.weights = reward_weights
        self.render_mode = render_mode

        self.model = build_model(self.object_spec, self.mass_scale)
        self.data = mujoco.MjData(self.model)
        self.ix = SceneIndex.of(self.model)
        # This episode's conditions: the fixed settings, or per-episode draws from the ranges.
        self.episode_mass_scale, self.episode_noise_std, self.episode_jitter = self.mass_scale, self.torque_noise_std, self.jitter
        self.randomisation_level = 1.0  # how much of the ranges is open (forcegrasp.curriculum); 1: all
        body = self.ix.object_body
        self._unit_mass = self.model.body_mass[body] / self.mass_scale
        self._unit_inertia = self.model.body_inertia[body] / self.mass_scale
        self.slides = slide_axes(self.model)
        self._rest_z = resting_height(self.model)
        self._action_scale = action_scale(max_translation_step, max_rotation_step, max_h_step)
        self._base_lo, self._base_hi = self.ix.all_range[:6, 0], self.ix.all_range[:6, 1]
        self._hand_span = self.ix.hand_range[:, 1] - self.ix.hand_range[:, 0]
        self._J0, self._Jg = self.label.pregrasp.hand, self.label.goal.hand
        self._dJ = self._Jg - self._J0
        # The hot path reads and writes MjData through views made once (each attribute access
        # builds a new array) and through slices: base and hand joints are contiguous blocks.
        d, ix = self.data, self.ix
        self._base_q, self._hand_q = block_view(d.qpos, ix.base_qpos), block_view(d.qpos, ix.hand_qpos)
        self._base_ctrl, self._hand_ctrl = block_view(d.ctrl, ix.base_act), block_view(d.ctrl, ix.hand_act)
        self._hand_force = block_view(d.actuator_force, ix.hand_act)
        self._object_pos = d.xpos[ix.object_body]
        self._palm_pos = d.site_xpos[ix.palm_site]
        self._inv_span = 1.0 / self._hand_span
        # Goal palm in the world with the object at its nominal pose (origin): Table I's last entry.
        self._goal_tail = np.concatenate([self.label.goal.base, self.label.goal_palm]).astype(np.float32)

        layout = observation_layout(self.force_feedback, torque_history, proprioception)  # checks both
        n_obs = sum(n for _, n in layout)
        # Table I is written into one buffer by slices (cheaper than concatenating 8 parts).
        edges = np.cumsum([0] + [n for _, n in layout])
        self._slots = {name: slice(a, b) for (name, _), a, b in zip(layout, edges, edges[1:])}
        self._proprio = [self._slots[COMMANDED_SLOTS[n] if self._commanded else n] for n in COMMANDED_SLOTS]
        self._obs = np.zeros(n_obs, np.float32)
        self._obs[self._slots["goal_pose"].start:] = self._goal_tail
        self._h_scratch = np.zeros(len(self._Jg))
        # Geom-id lookup tables: numpy's isin on a handful of contacts costs ~10 us, a table ~1 us.
        self._is_object_geom, self._is_hand_geom = np.zeros((2, self.model.ngeom), bool)
        self._is_object_geom[self.ix.object_geoms] = self._is_hand_geom[self.ix.hand_geoms] = True
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (n_obs,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (7,), np.float32)
        self._renderer = None
        self._probe = None  # scratch MjData for `overlap`
        self._fingertips = [self.ix.fingertip_geoms[f] for f in ("ff", "mf", "rf", "lf", "th")]

    @classmethod
    def for_policy(cls, meta, object_name: str | None = None, **kwargs) -> "FunctionalGraspEnv":
        """The env a policy file was trained for: its object, observation (force feedback, torque
        history, proprioception), action step sizes and training conditions (mass, noise, jitter and
        their per-episode ranges; ``meta`` is its PolicyMetadata). ``kwargs`` set everything else and
        override what the file records; a fixed ``mass_scale``, ``torque_noise_std`` or ``jitter`` turns
        the recorded range off (a test condition never randomises). ``object_name`` picks the object of a
        multi-object policy (whose file names none)."""
        recorded = dict(meta.extra.get("training_conditions") or {})
        for fixed, span in (("mass_scale", "mass_scale_range"), ("torque_noise_std", "torque_noise_range"),
                            ("jitter", "jitter_range")):
            if fixed in kwargs or not recorded.get(span):
                recorded.pop(span, None)
        if not (object_name or meta.object_name):
            raise ValueError("a policy of several objects: name the object to build its env for")
        return cls(object_name or meta.object_name, **{"force_feedback": meta.force_feedback, "torque_history": torque_history_of(meta),
                                        "proprioception": proprioception_of(meta), **action_steps_of(meta),
                                        **recorded, **kwargs})

    # ------------------------------------------------------------------ episode
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start at the pre-grasp with the object shifted by ``options["offset"]`` (dx, dy) in m, or
        by an offset drawn uniformly from the part of the ±jitter square where the pre-grasp hand
        does not overlap the object (near some edges it would start inside it; see `overlap`); with
        ``jitter_range`` the square's half-width is drawn first (the critic sees the offset).
        An explicit offset with an overlap is refused with ValueError.
        """
        super().reset(seed=seed)
        d = self.data
        offset = (options or {}).get("offset")
        if offset is None:
            self.episode_jitter = draw(self.np_random, self.jitter, self.jitter_range, self.randomisation_level)
            offset = draw_clear_offset(self.np_random, self.episode_jitter, self.is_clear, self.object_spec.name)
        else:
            offset = np.asarray(offset, dtype=float)
            if offset.shape != (2,) or not np.all(np.isfinite(offset)):
                raise ValueError(f"options['offset'] must be 2 finite numbers (dx, dy) in m, got {offset!r}")
            depth = self.overlap(offset)  # on the scratch data: a refused reset leaves the episode as it was
            if depth > OVERLAP_TOLERANCE:
                raise ValueError(f"{self.object_spec.name} at offset ({offset[0]:+.4f}, {offset[1]:+.4f}) m starts "
                                 f"{depth * 1000:.1f} mm inside the pre-grasp hand; choose a clear placement "
                                 "(FunctionalGraspEnv.overlap tells)")
        self._draw_conditions()
        self._start_pose(d, offset)
        self.offset = offset
        self.object_start = self._object_pos.copy()
        self.base_target = self.label.pregrasp.base.copy()
        self.h_command = 0.0
        self.steps = 0
        self.episode_return = 0.0
        self._prev_pose = self._base_q.copy()
        self._prev_h = self._observed_h()
        self._prev_target, self._prev_h_command = self.base_target, 0.0
        obs = self._observation()
        if self.torque_history:  # no earlier steps: the history starts as copies of the first reading
            at = self._slots
            self._obs[at["torque_history"]] = np.tile(self._obs[at["joint_torques"]], self.torque_history)
            obs = self._obs.copy()
        return obs, {"offset": offset.copy(), "h": self._prev_h}

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (7,) or not all(-_ACTION_LIMIT <= a <= _ACTION_LIMIT for a in action.tolist()):
            self._reject(action)  # NaN fails the comparison too
        delta = action * self._action_scale
        self._prev_pose = self._base_q.copy()
        self._prev_h = self._h_now
        self._prev_target, self._prev_h_command = self.base_target, self.h_command  # base_target: a new array below
        target = self.base_target + delta[:6]
        self.base_target = np.minimum(np.maximum(target, self._base_lo, out=target), self._base_hi, out=target)
        self.h_command = h = min(1.0, max(0.0, self.h_command + float(delta[6])))
        self._base_ctrl[:] = target
        np.multiply(self._dJ, h, out=self._hand_ctrl)  # J = h (Jg - J0) + J0, written into d.ctrl
        self._hand_ctrl += self._J0
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        self.steps += 1

        obs = self._observation()
        object_pos = self._object_pos
        outcome = evaluate_state(
            self._h_now,
            self._palm_pos - object_pos,
            self.label.goal_palm,
            object_pos,
            self.object_start,
            self.steps,
            self.max_steps,
            self.weights,
            self.object_tolerance,
            self.palm_tolerance,
            self.success_tolerances,
        )
        self.episode_return += outcome.reward
        failure = outcome.failure
        if failure is None and not outcome.success and self.episode_return < self.abort_return:
            failure = "low_return"
        terminated = outcome.success or failure is not None
        truncated = not terminated and self.steps >= self.max_steps
        info = {
            "r_a": outcome.r_a,
            "r_b": outcome.r_b,
            "r_c": outcome.r_c,
            "h": self._h_now,
            "object_displacement": -outcome.r_c,
            "palm_error": -outcome.r_b,
            "success": outcome.success,
            "failure": failure if failure is not None else ("time_limit" if truncated else None),
            "step": self.steps,
        }
        return obs, outcome.reward, terminated, truncated, info

    # ------------------------------------------------------------------ pieces
    def _reject(self, action: np.ndarray):
        what = (f"must have shape (7,), got {action.shape}" if action.shape != (7,) else f"must be finite, got {action}"
                if not np.all(np.isfinite(action)) else f"components must lie in [-1, 1], got {action}")
        raise ValueError(f"action {what}")

    def _draw_conditions(self) -> None:
        """Draw this episode's mass (log-uniform) and torque-noise sigma (uniform) from the part of
        their ranges ``randomisation_level`` opens (`widened`); a uniform density scales mass and
        inertia alike, and mj_setConst refreshes what depends on them."""
        level = self.randomisation_level
        self.episode_noise_std = draw(self.np_random, self.torque_noise_std, self.torque_noise_range, level)
        if self.mass_scale_range is not None:
            self.set_mass_scale(draw(self.np_random, self.mass_scale, self.mass_scale_range, level, log=True))

    def set_mass_scale(self, scale: float) -> None:
        """Make the object ``scale`` times its nominal mass from the next reset on."""
        if not np.isfinite(scale) or scale <= 0:
            raise ValueError(f"mass scale must be positive, got {scale!r}")
        body = self.ix.object_body
        self.model.body_mass[body] = self._unit_mass * scale
        self.model.body_inertia[body] = self._unit_inertia * scale
        mujoco.mj_setConst(self.model, self.data)
        self.episode_mass_scale = float(scale)

    def _observed_h(self) -> float:
        x = self._h_scratch
        np.multiply(np.abs(np.subtract(self._hand_q, self._Jg, out=x), out=x), self._inv_span, out=x)
        self._h_now = 1.0 - 0.5 * float(np.maximum.reduce(x))
        return self._h_now

    def _observation(self) -> np.ndarray:
        """Table I (see the module docstring), a fresh array; measures h (the reward's) in either mode."""
        h = self._observed_h()
        obs, at = self._obs, self._slots
        if self.force_feedback:
            if self.torque_history:  # shift by one step: the torques observed last go in front
                obs[at["torque_history"]] = np.roll(obs[at["torque_history"]], 24)
                obs[at["torque_history"]][:24] = obs[at["joint_torques"]]
            reading = self._hand_force + (self.np_random.normal(0.0, self.episode_noise_std, 24)
                                          if self.episode_noise_std > 0 else 0.0)
            a = self.torque_filter if self.steps else 1.0  # an episode's first reading starts the average
            obs[at["joint_torques"]] = a * reading + (1.0 - a) * obs[at["joint_torques"]]
        obs[at["base_targets"]] = self.base_target
        for slot, value in zip(self._proprio, (self._hand_ctrl, self.base_target, self.h_command, self._prev_target,
                                               self._prev_h_command) if self._commanded else
                               (self._hand_q, self._base_q, h, self._prev_pose, self._prev_h)):
            obs[slot] = value
        return obs.copy()

    def privileged_state(self) -> np.ndarray:
        """`PRIVILEGED_LAYOUT` for the current state (PRIV_DIM float32): what an asymmetric critic may
        see in simulation; never part of the observation."""
        d, ix = self.data, self.ix
        out = np.zeros(PRIV_DIM, np.float32)
        out[0:2] = 100.0 * self.offset
        out[2:5] = 100.0 * (self._palm_pos - self._object_pos - self.label.goal_palm)
        out[5:8] = 100.0 * (self._object_pos - self.object_start)
        other, _ = self._object_contacts(d)
        if other.size:
            for k, geom in enumerate(self._fingertips):
                out[8 + k] = float((other == geom).any())
            out[13] = float(self._is_hand_geom[other].any())
        out[DOMAIN] = np.log(self.episode_mass_scale), self.episode_noise_std
        return out

    def palm_position(self) -> np.ndarray:
        """The palm centre in the world (m), a copy: for trajectory plots, never observed."""
        return self._palm_pos.copy()

    def object_position(self) -> np.ndarray:
        """The object's origin in the world (m), a copy: for trajectory plots, never observed."""
        return self._object_pos.copy()

    def goal_base_for_offset(self, offset) -> np.ndarray:
        """Goal base joint values for an object displaced by (dx, dy): what an oracle would aim at."""
        shift = self.slides.T @ np.array([offset[0], offset[1], 0.0])
        return self.label.goal.base + np.concatenate([shift, np.zeros(3)])

    def is_clear(self, offset) -> bool:
        """Whether an episode can start with the object at `offset` (see `reset`)."""
        return self.overlap(offset) <= OVERLAP_TOLERANCE

    def overlap(self, offset) -> float:
        """How deep (m) the pre-grasp hand would start inside the object shifted by `offset`; 0 if
        clear. Uses a scratch MjData: the running episode is not touched."""
        if self._probe is None:
            self._probe = mujoco.MjData(self.model)
        self._start_pose(self._probe, np.asarray(offset, dtype=float), forward=False)
        mujoco.mj_kinematics(self.model, self._probe)  # contacts need only geom poses: no full mj_forward
        mujoco.mj_collision(self.model, self._probe)
        return self._overlap(self._probe)

    def _start_pose(self, d: mujoco.MjData, offset: np.ndarray, forward: bool = True) -> None:
        """Pre-grasp hand, object at rest at `offset`, servos holding the pre-grasp; mj_forward done
        unless ``forward`` is False."""
        m, ix = self.model, self.ix
        mujoco.mj_resetData(m, d)
        d.qpos[ix.all_qpos] = self.label.pregrasp.q
        d.qpos[ix.object_qpos : ix.object_qpos + 3] = (offset[0], offset[1], self._rest_z)
        d.qpos[ix.object_qpos + 3 : ix.object_qpos + 7] = (1.0, 0.0, 0.0, 0.0)
        d.ctrl[ix.base_act] = self.label.pregrasp.base
        d.ctrl[ix.hand_act] = self._J0
        if forward:
            mujoco.mj_forward(m, d)

    def _object_contacts(self, d: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """The geoms touching the object in `d` and each contact's distance (negative: penetration)."""
        n = d.ncon
        if n == 0:
            return np.empty(0, int), np.empty(0)
        contact = d.contact
        g1, g2, dist = contact.geom1[:n], contact.geom2[:n], contact.dist[:n]
        first = self._is_object_geom[g1]
        on_object = first | self._is_object_geom[g2]
        return np.where(first, g2, g1)[on_object], dist[on_object]

    def _overlap(self, d: mujoco.MjData) -> float:
        """Deepest hand-object penetration among `d`'s contacts (m), 0 if none."""
        other, dist = self._object_contacts(d)
        hand = self._is_hand_geom[other]
        return float(max(0.0, -dist[hand].min())) if hand.any() else 0.0

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        from forcegrasp.render import make_renderer, object_camera, render

        if self._renderer is None:
            self._renderer = make_renderer(self.model, 360, 480)
        return render(self._renderer, self.data, object_camera(self.object_spec.view, self.data.xpos[self.ix.object_body]))

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def register_envs() -> None:
    """Gymnasium ids FunctionalGrasp-<Object>-v0 for every object file, imported meshes included
    (mug_mesh -> FunctionalGrasp-MugMesh-v0); kwargs pass through to FunctionalGraspEnv."""
    from gymnasium.envs.registration import register, registry

    from forcegrasp.objects import list_objects

    for object_name in list_objects():
        env_id = f"FunctionalGrasp-{''.join(w.capitalize() for w in object_name.split('_'))}-v0"
        if env_id not in registry:
            register(id=env_id, entry_point="forcegrasp.env:FunctionalGraspEnv", kwargs={"object_name": object_name})


register_envs()
