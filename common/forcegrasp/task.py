"""The task contract, without the simulator: what a FunctionalGrasp policy sees and does.

Every size in ForceGrasp comes from here: the observation layout (Table I of the paper; 77 numbers,
53 without force feedback; 77 + 24 k with the optional torque history of k steps; the same sizes
under other names with ``commanded`` proprioception), the action layout (7), the privileged
simulator state an asymmetric critic may see in training (16, never part of the observation) and
what an action of +1 means in env units. `policy_metadata` builds the metadata of a policy for a task and `check_policy` tells
whether a policy file fits an env's settings. Importing this module loads neither mujoco nor
gymnasium, so protocol clients, the learner and tools can use it.
"""

from __future__ import annotations

import numpy as np

from forcegrasp.policy_file import PolicyMetadata

#: Table I, in order. Torques come first and are the part dropped without force feedback.
OBS_LAYOUT = (
    ("joint_torques", 24),
    ("joint_angles", 24),
    ("hand_pose", 6),
    ("h", 1),
    ("base_targets", 6),
    ("prev_hand_pose", 6),
    ("prev_h", 1),
    ("goal_pose", 6),
    ("goal_palm", 3),
)
#: What fills Table I's proprioceptive slots: ``measured`` (the paper's: joint angles, hand pose and
#: observed h, which a contact that stops a position servo shows) or ``commanded`` (what the policy
#: commanded there instead: the hand joint targets, base targets and commanded h, which no contact
#: changes; with force feedback off nothing observed then depends on the object). The first is the default.
PROPRIOCEPTION = ("measured", "commanded")
#: The Table I slots that ``commanded`` proprioception fills with commands, and their names there.
#: ``base_targets`` is a command already and keeps its name (and value: base_command repeats it).
COMMANDED_SLOTS = {
    "joint_angles": "joint_targets",  # J(h_cmd) = h_cmd (Jg - J0) + J0: the hand servos' ctrl
    "hand_pose": "base_command",  # the base servos' targets (= base_targets)
    "h": "h_command",  # the commanded h in [0, 1]
    "prev_hand_pose": "prev_base_command",  # base_command at the previous step
    "prev_h": "prev_h_command",  # h_command at the previous step
}
ACTION_LAYOUT = (("base_target_delta", 6), ("h_delta", 1))
ACT_DIM = sum(n for _, n in ACTION_LAYOUT)

# Simulator state the deployed policy never observes, for an asymmetric critic (learner only):
# where the object is (its jitter), where the palm is relative to its goal on the object, how far
# the object has been pushed (all three in cm, so that they are of order one like the flags), and
# which fingertips (ff mf rf lf th) and whether any part of the hand touch it.
PRIVILEGED_LAYOUT = (
    ("object_offset", 2),
    ("palm_error", 3),
    ("object_displacement", 3),
    ("fingertip_contacts", 5),
    ("hand_contact", 1),
    ("domain", 2),  # this episode's ln(mass scale) and torque-noise sigma (N*m): the randomised conditions
)
PRIV_DIM = sum(n for _, n in PRIVILEGED_LAYOUT)
DOMAIN = slice(PRIV_DIM - 2, PRIV_DIM)  # the "domain" entry, last
TORQUES = slice(0, 24)  # joint_torques in an observation with force feedback (OBS_LAYOUT's first slot)

#: Largest change per step of the base translation targets (m), rotation targets (rad) and h: the
#: recipe's default (docs/recipe.md).
ACTION_STEPS = (0.006, 0.03, 0.0375)
#: Their names as FunctionalGraspEnv keywords and `env.*` configuration keys.
ACTION_STEP_KEYS = ("max_translation_step", "max_rotation_step", "max_h_step")


def observation_layout(force_feedback: bool = True, torque_history: int = 0,
                       proprioception: str = "measured") -> tuple[tuple[str, int], ...]:
    """Table I; with ``torque_history`` k > 0 the joint torques of the k previous steps (newest
    first, 24 each) follow the current ones: a lever outside the paper's observation. With
    ``proprioception="commanded"`` the slots of `COMMANDED_SLOTS` carry their commanded names
    (same sizes, same order)."""
    check_torque_history(force_feedback, torque_history)
    check_proprioception(proprioception)
    table = OBS_LAYOUT if proprioception == "measured" else tuple(
        (COMMANDED_SLOTS.get(name, name), n) for name, n in OBS_LAYOUT)
    if not force_feedback:
        return table[1:]
    history = (("torque_history", 24 * int(torque_history)),) if torque_history else ()
    return (table[0], *history, *table[1:])


def obs_dim(force_feedback: bool = True, torque_history: int = 0, proprioception: str = "measured") -> int:
    return sum(n for _, n in observation_layout(force_feedback, torque_history, proprioception))


def check_torque_history(force_feedback: bool, torque_history: int) -> None:
    if int(torque_history) != torque_history or torque_history < 0:
        raise ValueError(f"torque_history must be a whole number >= 0, got {torque_history!r}")
    if torque_history and not force_feedback:
        raise ValueError("torque_history needs force_feedback: without it no torques are observed")


def check_proprioception(proprioception: str) -> None:
    if proprioception not in PROPRIOCEPTION:
        raise ValueError(f"proprioception must be one of {', '.join(PROPRIOCEPTION)}, got {proprioception!r}")


def torque_history_of(meta: PolicyMetadata) -> int:
    """How many previous steps' torques a policy observes (0 for Table I itself)."""
    return dict(meta.obs_layout).get("torque_history", 0) // 24


def proprioception_of(meta: PolicyMetadata) -> str:
    """What fills a policy's proprioceptive slots: ``commanded`` when its layout names the commanded
    slots, else ``measured`` (Table I itself, and every file from before the mode existed)."""
    return "commanded" if "joint_targets" in dict(meta.obs_layout) else "measured"


def action_scale(max_translation_step: float = ACTION_STEPS[0], max_rotation_step: float = ACTION_STEPS[1],
                 max_h_step: float = ACTION_STEPS[2]) -> np.ndarray:
    """What action +1 means in env units, per component: the policy file's ``action_high``."""
    for name, step in zip(ACTION_STEP_KEYS, (max_translation_step, max_rotation_step, max_h_step)):
        if not np.isfinite(step) or step <= 0:
            raise ValueError(f"{name} must be positive, got {step!r}")
    return np.array([max_translation_step] * 3 + [max_rotation_step] * 3 + [max_h_step])


def action_steps_of(meta: PolicyMetadata) -> dict[str, float]:
    """The action step sizes a policy was trained with (FunctionalGraspEnv keywords), read from the
    ``action_high`` its file records."""
    high = meta.action_high
    if high is None:
        raise ValueError("the policy records no action_high, so the action step sizes it was trained with are unknown")
    return dict(zip(ACTION_STEP_KEYS, (float(high[0]), float(high[3]), float(high[6]))))


def policy_metadata(object_name: str, force_feedback: bool, hidden, *, obs_norm: bool = False,
                    training_steps: int = 0, score: float | None = None, action_steps: dict | None = None,
                    torque_history: int = 0, proprioception: str = "measured",
                    extra: dict | None = None) -> PolicyMetadata:
    """The metadata of a policy for this task: layouts (the observation's records ``torque_history``
    and ``proprioception``), action scaling (``action_steps``: the env's step-size keywords, default
    `ACTION_STEPS`), architecture."""
    scale = action_scale(**(action_steps or {}))
    return PolicyMetadata(
        obs_layout=list(observation_layout(force_feedback, torque_history, proprioception)),
        action_layout=list(ACTION_LAYOUT),
        hidden=tuple(hidden),
        object_name=object_name,
        force_feedback=bool(force_feedback),
        training_steps=int(training_steps),
        eval_score=score,
        obs_norm=bool(obs_norm),
        action_low=[-float(x) for x in scale],
        action_high=[float(x) for x in scale],
        extra=dict(extra or {}),
    )


def check_policy(meta: PolicyMetadata, object_name: str | None = None, force_feedback: bool | None = None,
                 action_steps: dict | None = None, torque_history: int = 0, proprioception: str = "measured") -> None:
    """Raise ValueError saying why a policy does not fit an env with these settings (``action_steps``:
    the env's step-size keywords, default `ACTION_STEPS`; ``torque_history``, ``proprioception``: the env's)."""
    ff = meta.force_feedback if force_feedback is None else bool(force_feedback)
    layout = observation_layout(ff, torque_history, proprioception)
    if meta.obs_layout != list(layout):
        setting = f"force_feedback={ff}" + (f", torque_history={torque_history}" if torque_history else "")
        mode = proprioception_of(meta)
        if mode != proprioception:  # the same sizes mean other things: say which before the names
            raise ValueError(f"policy observes {mode} proprioception ({[n for n, _ in meta.obs_layout]}); the env "
                             f"with {setting}, proprioception={proprioception} observes {proprioception} "
                             f"proprioception ({[n for n, _ in layout]})")
        if proprioception != "measured":
            setting += f", proprioception={proprioception}"
        raise ValueError(f"policy observes {meta.obs_dim} numbers ({[n for n, _ in meta.obs_layout]}); "
                         f"the env with {setting} gives {obs_dim(ff, torque_history, proprioception)} "
                         f"({[n for n, _ in layout]})")
    if meta.action_layout != list(ACTION_LAYOUT):
        raise ValueError(f"policy acts with {meta.act_dim} numbers {meta.action_layout}; the env takes {ACTION_LAYOUT}")
    if object_name is not None and meta.object_name and meta.object_name != object_name:
        raise ValueError(f"policy is for object {meta.object_name!r}, the env holds {object_name!r}")
    check_action_steps(meta, action_steps)


def check_action_steps(meta: PolicyMetadata, action_steps: dict | None = None) -> None:
    """Raise ValueError when a policy records other action step sizes than an env's (``action_steps``:
    its step-size keywords, default `ACTION_STEPS`) or records none."""
    scale = action_scale(**(action_steps or {}))
    if meta.action_high is None:
        raise ValueError(f"policy records no action steps (action_high); the env uses {scale.tolist()}")
    if not np.allclose(meta.action_high, scale):
        raise ValueError(f"policy was trained with action steps {meta.action_high}, the env uses {scale.tolist()}")
