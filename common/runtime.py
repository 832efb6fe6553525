"""Plumbing every service shares: its Zenoh session, its stop signal, its env and policy layout.

Kept here so the actor, learner and evaluator modules read as their role and nothing else.
"""

from __future__ import annotations

import signal
import threading

import zenoh

from forcegrasp.config import Config
from forcegrasp.env import ACTION_LAYOUT, FunctionalGraspEnv, action_scale, observation_layout
from forcegrasp.policy_file import PolicyMetadata, actor_param_shapes
from forcegrasp.transport import open_session


def open_service_session(config: Config, service: str) -> zenoh.Session:
    """The learner listens on its endpoints; every other service connects to it (and listens)."""
    listen, connect = config.network.endpoints_for(service)
    return open_session(
        listen,
        connect,
        mode=config.network.mode,
        lease_ms=config.network.lease_ms,
        config_file=config.network.zenoh_config or None,
    )


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM: services finish their loop step and close cleanly."""
    stop = threading.Event()

    def handler(signum, frame):
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)
    return stop


def make_env(config: Config, **overrides) -> FunctionalGraspEnv:
    e = config.env
    kwargs = dict(
        force_feedback=e.force_feedback,
        mass_scale=e.mass_scale,
        jitter=e.jitter,
        torque_noise_std=e.torque_noise_std,
        max_steps=e.max_steps,
    )
    kwargs.update(overrides)
    return FunctionalGraspEnv(e.object, **kwargs)


def policy_metadata(config: Config, hidden, training_steps: int = 0, score: float | None = None,
                    obs_norm: bool = False, **extra) -> PolicyMetadata:
    """What a policy trained under ``config`` looks like: the contract between learner and actors."""
    return PolicyMetadata(
        obs_layout=list(observation_layout(config.env.force_feedback)),
        action_layout=list(ACTION_LAYOUT),
        hidden=tuple(hidden),
        object_name=config.env.object,
        force_feedback=config.env.force_feedback,
        training_steps=training_steps,
        eval_score=score,
        obs_norm=obs_norm,
        action_low=[-float(x) for x in action_scale()],
        action_high=[float(x) for x in action_scale()],
        extra={"run": config.run.name, **extra},
    )


def expected_weight_shapes(config: Config, hidden) -> dict[str, tuple[int, ...]]:
    return actor_param_shapes(policy_metadata(config, hidden))
