"""Plumbing every service shares: its Zenoh session, its stop signal, its env and policy layout.

Kept here so the actor, learner and evaluator modules read as their role and nothing else.
"""

from __future__ import annotations

import signal
import threading

import zenoh

from forcegrasp.config import Config, ConfigError
from forcegrasp import task
from forcegrasp.policy_file import PolicyMetadata
from forcegrasp.transport import open_session


def open_service_session(config: Config, service: str, identity: str | None = None,
                         connect_timeout_ms: int = -1) -> zenoh.Session:
    """The learner listens on its endpoints; every other service connects to it (and listens).

    With ``network.credentials`` (`forcegrasp.security`) the learner is a TLS router with access
    control and the others its clients, as `identity` (default: the service's name; an actor's
    is its id up to the first '.', so ``actor-3.host7`` speaks as ``actor-3``)."""
    net = config.network
    listen, connect = net.endpoints_for(service)
    extra = None
    mode = net.mode
    if net.credentials:
        from forcegrasp.security import credentials_folder, session_settings

        plain = [e for e in listen + connect if not e.startswith("tls/")]
        if plain:
            raise ConfigError(f"network.credentials is set, so endpoints must be tls/HOST:PORT, not {', '.join(plain)}")
        name = identity or ("client" if service == "monitor" else service)
        extra = session_settings(credentials_folder(net.credentials, name), service, config.run.name,
                                 mutual_tls=net.mutual_tls, connect_timeout_ms=connect_timeout_ms)
        mode = extra.pop("mode")
    return open_session(
        listen,
        connect,
        mode=mode,
        lease_ms=net.lease_ms,
        shared_memory=net.shared_memory,
        config_file=net.zenoh_config or None,
        extra=extra,
    )


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM: services finish their loop step and close cleanly."""
    stop = threading.Event()

    def handler(signum, frame):
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)
    return stop


def make_env(config: Config, object_name: str | None = None, **overrides):
    """The FunctionalGraspEnv of this configuration (imports the simulator only when called), for
    ``object_name`` (default ``env.object``: with ``env.objects``, its first entry)."""
    from forcegrasp.env import FunctionalGraspEnv

    e = config.env
    kwargs = dict(
        force_feedback=e.force_feedback,
        mass_scale=e.mass_scale,
        jitter=e.jitter,
        torque_noise_std=e.torque_noise_std,
        max_steps=e.max_steps,
        torque_history=e.torque_history,
        torque_filter=e.torque_filter,
        proprioception=e.proprioception,
        mass_scale_range=e.mass_scale_range or None,
        torque_noise_range=e.torque_noise_range or None,
        jitter_range=e.jitter_range or None,
        **e.action_steps(),
    )
    kwargs.update(overrides)
    return FunctionalGraspEnv(object_name or e.object, **kwargs)


def policy_metadata(config: Config, hidden, training_steps: int = 0, score: float | None = None,
                    obs_norm: bool = False, **extra) -> PolicyMetadata:
    """What a policy trained under ``config`` looks like: the contract between learner and actors.
    With several ``env.objects`` it names no one object: ``extra["objects"]`` records the set."""
    objects = config.env.objects if len(config.env.objects) > 1 else []
    if objects:
        extra = {"objects": list(objects), **extra}
    return task.policy_metadata("" if objects else config.env.object, config.env.force_feedback, hidden,
                                obs_norm=obs_norm,
                                training_steps=training_steps, score=score, action_steps=config.env.action_steps(),
                                torque_history=config.env.torque_history,
                                proprioception=config.env.proprioception,
                                extra={"run": config.run.name, "training_conditions": training_conditions(config),
                                       **curriculum_of(config), **extra})


def training_conditions(config: Config) -> dict:
    """The physics and sensing a policy was trained under (its file records them, so that an env
    rebuilt from the file reproduces them): fixed values, the per-episode ranges when set, and a
    torque filter (part of the policy's sensing: every test of the policy keeps it)."""
    e = config.env
    return {"mass_scale": e.mass_scale, "torque_noise_std": e.torque_noise_std, "jitter": e.jitter,
            "mass_scale_range": list(e.mass_scale_range), "torque_noise_range": list(e.torque_noise_range),
            **({"jitter_range": list(e.jitter_range)} if e.jitter_range else {}),
            **({"torque_filter": e.torque_filter} if e.torque_filter < 1 else {})}


def curriculum_of(config: Config) -> dict:
    """The randomisation curriculum a policy was trained with, for its file (empty when off)."""
    e = config.env
    if not e.curriculum_success:
        return {}
    return {"randomisation_curriculum": {"success": e.curriculum_success, "window": e.curriculum_window,
                                         "stages": e.curriculum_stages}}
