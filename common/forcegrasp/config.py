"""One configuration for every ForceGrasp service: TOML file, then environment, then flags.

All services (learner, actors, evaluator, launcher) read the same :class:`Config`, so a run is
described in one place.  Values come from, in increasing precedence:

1. the dataclass defaults below (printed by :func:`forcegrasp.config_toml.default_config_toml`, also ``configs/default.toml``);
2. a TOML file (``--config PATH`` or ``FORCEGRASP_CONFIG``);
3. environment variables ``FORCEGRASP_<SECTION>_<KEY>`` (e.g. ``FORCEGRASP_ACTOR_ENVS_PER_ACTOR=4``;
   ``FORCEGRASP_LEARNER_SAC_BATCH_SIZE=128`` for an entry of ``[learner.sac]``);
4. command-line ``--set section.key=value`` (e.g. ``--set learner.sac.gamma=0.98``).

String values (environment, flags) are coerced to the field's type; anything unknown or of the
wrong type raises :class:`ConfigError` naming the key.  SAC hyper-parameters are owned by
``forcegrasp.sac.SACConfig``: ``[learner.sac]`` only carries overrides, validated there.
Environment variables whose section is not one of ours (e.g. ``FORCEGRASP_ASSETS``) are ignored.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from forcegrasp.config_values import ConfigError, coerce as _coerce, parse_literal as _parse_literal  # noqa: F401
from forcegrasp.conditions import ROBUST_MIX
from forcegrasp.multi_object import SAMPLING as OBJECT_SAMPLING
from forcegrasp.task import ACTION_STEPS, PROPRIOCEPTION

ENV_PREFIX = "FORCEGRASP_"
CONFIG_FILE_ENV = "FORCEGRASP_CONFIG"


def _f(default: Any, help: str, *, min: float | None = None, choices: Sequence[str] | None = None):
    """Dataclass field carrying its documentation and simple bounds (used for checks and the TOML)."""
    meta = {"help": help, "min": min, "choices": tuple(choices) if choices else None}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass
class RunConfig:
    """Naming and output of one training run."""

    name: str = _f("default", "run name: Zenoh keys forcegrasp/<name>/... and the output folder")
    output_dir: str = _f("runs", "checkpoints, replay snapshots, logs go to <output_dir>/<name>/")
    seed: int = _f(0, "base seed; actor i uses seed + 1000 * (i + 1)", min=0)


@dataclass
class EnvConfig:
    """The FunctionalGrasp environment every actor and the evaluator build."""

    object: str = _f("mug", "object name (a file under assets/objects/); with env.objects, its first entry")
    objects: list[str] = _f([], "objects trained in one run by one learner (forcegrasp.multi_object: env j of actor i "
                                "steps objects[(i * envs_per_actor + j) % len]; the evaluator scores each; empty: "
                                "env.object alone)")
    object_sampling: str = _f("fixed", "with env.objects: fixed (each env keeps its assigned object) or adaptive (each "
                                       "episode's object drawn towards those the actor fails, forcegrasp.multi_object; "
                                       "a lever reported apart)", choices=OBJECT_SAMPLING)
    force_feedback: bool = _f(True, "observe joint torques (false: the paper's ablation, 53-dim obs)")
    mass_scale: float = _f(5.0, "object mass multiplier (5 for training, as in the paper)", min=0.0)
    jitter: float = _f(0.02, "object x-y start jitter, metres (uniform within +-jitter)", min=0.0)
    torque_noise_std: float = _f(0.0, "Gaussian noise on observed torques, N*m", min=0.0)
    # Domain randomisation, on by default (the robust recipe, docs/recipe.md): drawn afresh every
    # training episode, recorded in every policy file and seen by the asymmetric critic
    # (task.PRIVILEGED_LAYOUT "domain" and the offset), never by the policy. All three empty: the
    # paper's fixed conditions.
    mass_scale_range: list[float] = _f([0.5, 5.0], "per-episode mass multiplier drawn log-uniformly from [low, high] "
                                                   "(empty: mass_scale in every episode, as the paper trains)")
    torque_noise_range: list[float] = _f([0.0, 1.0], "per-episode torque noise sigma drawn uniformly from [low, high] "
                                                     "N*m (empty: torque_noise_std in every episode, as the paper trains)")
    jitter_range: list[float] = _f([0.02, 0.04], "per-episode half-width of the placement square drawn uniformly from [low, high] m, "
                                       "then the offset within it (empty: jitter in every episode, as the paper trains; tests use jitter)")
    curriculum_success: float = _f(0.0, "open the randomisation ranges in curriculum_stages steps from the fixed values, "
                                        "each once an actor's last curriculum_window policy episodes succeeded this "
                                        "often (forcegrasp.curriculum; 0: the full ranges from the first episode)", min=0.0)
    curriculum_window: int = _f(100, "policy episodes per actor that decide each curriculum stage", min=1)
    curriculum_stages: int = _f(5, "steps from the fixed values to the full randomisation ranges", min=1)
    max_steps: int = _f(200, "episode length limit", min=1)
    torque_history: int = _f(0, "joint torques of this many previous steps added to the observation (24 each; "
                                "changes Table I: a lever reported apart, never the default)", min=0)
    torque_filter: float = _f(1.0, "weight of the newest reading in an exponential moving average of the observed "
                                   "torques, noise included (1: the raw reading of Table I; < 1: a low-pass filter, "
                                   "a lever reported apart)", min=0.01)
    proprioception: str = _f("measured", "measured (Table I) or commanded: the servo targets and h the policy sent in "
                             "place of the measured angles, pose and h (a lever apart)", choices=PROPRIOCEPTION)
    # Action step sizes: what action +1 moves per step (a recipe lever; policy files record them;
    # task.ACTION_STEPS is the one place their defaults live).
    max_translation_step: float = _f(ACTION_STEPS[0], "base translation per step at action +1, metres", min=1e-6)
    max_rotation_step: float = _f(ACTION_STEPS[1], "base rotation per step at action +1, radians", min=1e-6)
    max_h_step: float = _f(ACTION_STEPS[2], "pre-grasp-to-goal hand interpolation per step at action +1", min=1e-6)

    def action_steps(self) -> dict[str, float]:
        """The step sizes as FunctionalGraspEnv / `forcegrasp.task.action_scale` keywords."""
        return {"max_translation_step": self.max_translation_step, "max_rotation_step": self.max_rotation_step,
                "max_h_step": self.max_h_step}


@dataclass
class ActorConfig:
    """Actor processes: envs, exploration, publishing."""

    num_actors: int = _f(2, "actor processes started by 'forcegrasp up'", min=0)
    envs_per_actor: int = _f(8, "environments stepped together in one actor process", min=1)
    random_steps: int = _f(1000, "uniformly random actions for this many env steps per actor", min=0)
    demo_episodes: int = _f(-1, "episodes per env of the scripted approach told the true object offset, "
                                "played first: demonstrations for the replay buffer (0: none; -1: the "
                                "recipe's number, forcegrasp.recipes.DEMOS_PER_ENV)", min=-1)
    demo_noise: float = _f(0.0, "std of Gaussian noise on the demonstrations' actions (action units)", min=0.0)
    publish_batch: int = _f(64, "transitions per published TransitionBatch", min=1)
    max_buffered_batches: int = _f(2000, "batches kept while the learner is away (oldest dropped)", min=1)


@dataclass
class NetworkConfig:
    """Zenoh endpoints.  The learner listens; every other service connects to it."""

    mode: str = _f("peer", "Zenoh mode; peer survives any start order", choices=("peer", "client", "router"))
    learner_listen: list[str] = _f(["tcp/127.0.0.1:7447"], "endpoints the learner listens on")
    connect: list[str] = _f([], "endpoints other services connect to (empty: learner_listen)")
    listen: list[str] = _f(["tcp/127.0.0.1:0"], "endpoints other services listen on (port 0: any), so peers mesh")
    lease_ms: int = _f(3000, "Zenoh lease: a hung (not killed) peer counts as gone after this", min=100)
    zenoh_config: str = _f("", "optional Zenoh JSON5 file applied first (settings ForceGrasp does not set)")
    credentials: str = _f("", "folder from 'forcegrasp certs DIR' (DIR, or one identity's DIR/<identity>): TLS, "
                              "user/password and the learner's access control; endpoints must be tls/ (docs/security.md)")
    mutual_tls: bool = _f(True, "with credentials: every service shows its certificate, not only the learner")
    shared_memory: bool = _f(False, "Zenoh shared memory between services on one machine; off because a receiver "
                                    "keeps every sender's 16 MB segment after the sender exits (eclipse-zenoh/zenoh#2787), "
                                    "so each actor restart grew the learner and /dev/shm (bench/soak.py)")

    def connect_endpoints(self) -> list[str]:
        """Where non-learner services connect: ``connect`` or the learner's listen endpoints.

        A learner listening on every interface (0.0.0.0 / [::]) is reached through loopback.
        """
        if self.connect:
            return list(self.connect)
        return [e.replace("/0.0.0.0:", "/127.0.0.1:").replace("/[::]:", "/[::1]:") for e in self.learner_listen]

    def endpoints_for(self, service: str) -> tuple[list[str], list[str]]:
        """``(listen, connect)`` for a service: the learner listens, the others connect."""
        if service == "learner":
            return list(self.learner_listen), []
        if self.credentials:  # the secure hub: clients of the learner's router listen on nothing
            return [], self.connect_endpoints()
        return list(self.listen), self.connect_endpoints()


@dataclass
class LearnerConfig:
    """Learner service knobs; SAC hyper-parameters go in [learner.sac] (see forcegrasp.sac.SACConfig)."""

    broadcast_every: int = _f(100, "gradient updates between weight broadcasts", min=1)
    max_lead: int = _f(2048, "transitions the actors may run ahead of updates / updates_per_step (0: no rate limit)",
                       min=0)
    checkpoint_every: int = _f(10000, "environment steps (transitions ingested) between checkpoints", min=1)
    snapshot_replay: bool = _f(True, "save the replay buffer with checkpoints, so a restart resumes it")
    ingest_queue: int = _f(1024, "received batches waiting to be decoded (the Zenoh callback's queue)", min=1)
    stats_every_s: float = _f(2.0, "seconds between stats messages and TensorBoard scalars", min=0.1)
    max_payload_mb: int = _f(64, "messages larger than this are rejected unread", min=1)
    recipe: str = _f("fast", "SAC preset under the [learner.sac] overrides, with its per-object settings "
                            "(forcegrasp.recipes.OBJECT_RECIPES; docs/recipe.md): fast or paper",
                     choices=("fast", "paper"))
    sac: dict[str, Any] = _f({}, "overrides of forcegrasp.sac.SACConfig fields, e.g. batch_size = 256")


@dataclass
class EvaluatorConfig:
    """Evaluator service: periodic evaluation, top-k checkpoints, final ranking, HTTP view."""

    eval_every: int = _f(2000, "environment steps between evaluations", min=1)
    eval_episodes: int = _f(4, "episodes per periodic evaluation, per test condition", min=1)
    top_k: int = _f(5, "best checkpoints kept", min=1)
    final_rank_episodes: int = _f(20, "episodes per top-k checkpoint and test condition in the final ranking", min=1)
    object_aggregate: str = _f("min", "how a checkpoint's per-object scores (with env.objects) make its score: "
                                      "min (as good as its worst object) or mean", choices=("min", "mean"))
    conditions: list[str] = _f(list(ROBUST_MIX), "test conditions a checkpoint is scored on, each with eval_episodes "
                               "and final_rank_episodes episodes, ranked on their mean (forcegrasp.conditions: 5x, "
                               "1x_3cm, 0.5x_3cm, 1x_1cm, 0.5x_1cm, noise_0.5, jitter_3cm); empty: the run's own env")
    cpu_share: float = _f(0.5, "the evaluator service's CPU budget as a fraction of one core (it pauses between "
                               "evaluations to stay within it; 1: no pause)", min=0.05)
    keep_episode_logs: str = _f("top", "MCAP episode logs kept: of the top-k checkpoints and the latest, or all",
                                choices=("top", "all"))
    http_host: str = _f("127.0.0.1", "address of the evaluator's HTTP page")
    http_port: int = _f(8080, "port of the evaluator's HTTP page (0: any free port)", min=0)


@dataclass
class Config:
    """Every section, in file order."""

    run: RunConfig = field(default_factory=RunConfig)
    env: EnvConfig = field(default_factory=EnvConfig)
    actor: ActorConfig = field(default_factory=ActorConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    evaluator: EvaluatorConfig = field(default_factory=EvaluatorConfig)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return dataclasses.asdict(self)

    def to_toml(self) -> str:
        """The resolved configuration, e.g. to record next to a run's checkpoints."""
        from forcegrasp.config_toml import emit_toml

        return emit_toml(self, comments=False)


SECTIONS: dict[str, type] = {f.name: f.default_factory for f in dataclasses.fields(Config)}  # type: ignore[misc]


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------

def load_config(path: str | os.PathLike | None = None, *, env: Mapping[str, str] | None = None,
                overrides: Iterable[str] = ()) -> Config:
    """Defaults, then the TOML file, then ``FORCEGRASP_*`` variables, then ``section.key=value`` overrides.

    ``env`` defaults to ``os.environ``; ``path`` defaults to ``$FORCEGRASP_CONFIG`` if set.
    """
    env = os.environ if env is None else env
    path = path if path is not None else (env.get(CONFIG_FILE_ENV) or None)
    config = Config()
    if path is not None:
        _apply_file(config, Path(path))
    for name, value in sorted(env.items()):
        target = _env_target(name)
        if target is not None:
            _set(config, *target, value, source=f"environment variable {name}")
    for item in overrides:
        section, key, value = _split_override(item)
        _set(config, section, key, value, source=f"--set {item}")
    _check_cross_fields(config)
    return config


def _apply_file(config: Config, path: Path) -> None:
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from None
    for section, table in data.items():
        if section not in SECTIONS:
            raise ConfigError(f"{path}: unknown section [{section}] (known: {', '.join(SECTIONS)})")
        if not isinstance(table, dict):
            raise ConfigError(f"{path}: {section} must be a table [{section}]")
        for key, value in table.items():
            _set(config, section, key, value, source=str(path))


def _env_target(name: str) -> tuple[str, str] | None:
    """``FORCEGRASP_ACTOR_ENVS_PER_ACTOR`` -> ("actor", "envs_per_actor"); None if not ours."""
    if not name.startswith(ENV_PREFIX) or name == CONFIG_FILE_ENV:
        return None
    section, _, key = name[len(ENV_PREFIX):].lower().partition("_")
    if section not in SECTIONS:
        return None
    if not key:
        raise ConfigError(f"environment variable {name}: missing key after the section")
    for fname, ftype in _types(section).items():  # FORCEGRASP_LEARNER_SAC_GAMMA: a dict entry
        if typing.get_origin(ftype) is dict and key.startswith(fname + "_"):
            return section, f"{fname}.{key[len(fname) + 1:]}"
    return section, key


def _split_override(item: str) -> tuple[str, str, str]:
    """``"learner.sac.gamma=0.98"`` -> ("learner", "sac.gamma", "0.98")."""
    dotted, sep, value = item.partition("=")
    section, dot, key = dotted.strip().partition(".")
    if not sep or not dot or not key:
        raise ConfigError(f"--set {item!r}: expected section.key=value")
    if section not in SECTIONS:
        raise ConfigError(f"--set {item!r}: unknown section {section!r} (known: {', '.join(SECTIONS)})")
    return section, key, value.strip()


def _fields(section: str) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(SECTIONS[section])}


def _types(section: str) -> dict[str, Any]:
    return typing.get_type_hints(SECTIONS[section])


def _set(config: Config, section: str, key: str, value: Any, *, source: str) -> None:
    """Set ``section.key`` (``key`` may be ``dictfield.entry``) after coercion and checks."""
    table = getattr(config, section)
    name, _, entry = key.partition(".")
    fields = _fields(section)
    full = f"{section}.{key}"
    if name not in fields:
        raise ConfigError(f"{source}: unknown key {full!r} (known in [{section}]: {', '.join(fields)})")
    ftype = _types(section)[name]
    if typing.get_origin(ftype) is dict:
        _set_dict(table, name, entry, value, full, source)
        return
    if entry:
        raise ConfigError(f"{source}: {section}.{name} is not a table, cannot set {full!r}")
    coerced = _coerce(value, ftype, full, source)
    _check_bounds(fields[name], coerced, full, source)
    setattr(table, name, coerced)


def _set_dict(table: Any, name: str, entry: str, value: Any, full: str, source: str) -> None:
    """Dict fields (``learner.sac``) take a whole table from TOML or one entry per env/flag."""
    current = getattr(table, name)
    if not entry:
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: {full} must be a table")
        current.update(value)
        return
    if not entry.isidentifier():
        raise ConfigError(f"{source}: {full!r} is not a valid entry name")
    current[entry] = _parse_literal(value) if isinstance(value, str) else value


def _check_bounds(f: dataclasses.Field, value: Any, key: str, source: str) -> None:
    low, choices = f.metadata.get("min"), f.metadata.get("choices")
    if low is not None and value < low:
        raise ConfigError(f"{source}: {key} = {value!r} must be >= {low}")
    if choices and value not in choices:
        raise ConfigError(f"{source}: {key} = {value!r} must be one of {', '.join(choices)}")


def _check_cross_fields(config: Config) -> None:
    """Rules involving more than one value, or the protocol's naming rules."""
    from forcegrasp.protocol import ProtocolError, validate_name

    try:
        validate_name(config.run.name, "run name")
    except ProtocolError as exc:
        raise ConfigError(f"run.name: {exc.detail}") from None
    from forcegrasp.objects import list_objects

    if config.env.objects:  # one run, several objects: env.object names the first (forcegrasp.multi_object)
        if len(set(config.env.objects)) != len(config.env.objects) or len(config.env.objects) > 255:
            raise ConfigError(f"env.objects = {config.env.objects!r}: at most 255 objects, each named once")
        config.env.object = config.env.objects[0]
    for name in config.env.objects or [config.env.object]:
        if name not in list_objects():
            # Fail here, before any service starts: a cluster of actors that each die on an unknown
            # object and are restarted forever says less than one line.
            raise ConfigError(f"env.object{'s' if config.env.objects else ''}: unknown object {name!r}; valid "
                              f"objects: {', '.join(list_objects())}")
    for key, low in (("mass_scale_range", 0.0), ("torque_noise_range", None), ("jitter_range", None)):
        span = getattr(config.env, key)
        if span and (len(span) != 2 or span[0] > span[1] or span[0] < 0 or (low is not None and span[0] <= low)):
            raise ConfigError(f"env.{key} = {span!r} must be empty or [low, high] with "
                              f"{'0 < low' if low is not None else '0 <= low'} <= high")
    if config.env.curriculum_success > 1 or (config.env.curriculum_success and not (
            config.env.mass_scale_range or config.env.torque_noise_range or config.env.jitter_range)):
        raise ConfigError(f"env.curriculum_success = {config.env.curriculum_success!r} must be in [0, 1] and needs "
                          "env.mass_scale_range, env.torque_noise_range or env.jitter_range to open")
    from forcegrasp.conditions import check_conditions
    from forcegrasp.recipes import sac_config

    if sac_config(config).actor_torque_noise and not config.env.force_feedback:  # every key and value checked too
        raise ConfigError("learner.sac.actor_torque_noise needs env.force_feedback = true: without it no torques "
                          "are observed")

    try:
        check_conditions(config.evaluator.conditions, "evaluator.conditions")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    if config.env.torque_filter > 1 or (config.env.torque_filter < 1 and not config.env.force_feedback):
        raise ConfigError(f"env.torque_filter = {config.env.torque_filter!r} must be in (0, 1] (1: no filter), "
                          "and below 1 only with env.force_feedback = true (it filters the observed torques)")
    if config.env.torque_history and not config.env.force_feedback:
        raise ConfigError("env.torque_history needs env.force_feedback = true: without it no torques are observed")
    if not config.network.learner_listen:
        raise ConfigError("network.learner_listen: at least one endpoint is needed")
    for key in ("learner_listen", "connect", "listen"):
        for endpoint in getattr(config.network, key):
            if "/" not in endpoint:
                raise ConfigError(f"network.{key}: {endpoint!r} is not an endpoint like tcp/127.0.0.1:7447")
    if config.network.credentials:
        used = config.network.connect_endpoints()  # the learner's own listen is checked as it opens
        plain = [e for e in used if not e.startswith("tls/")]
        if plain:  # a credentials folder with a tcp/ endpoint would send the passwords in the clear
            raise ConfigError(f"network.credentials is set, so endpoints must be tls/HOST:PORT, not {', '.join(plain)}")


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------

def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """``--config PATH`` and repeatable ``--set section.key=value`` for any sub-command."""
    parser.add_argument("--config", metavar="PATH", default=None,
                        help=f"TOML configuration file (default: ${CONFIG_FILE_ENV} or built-in defaults)")
    parser.add_argument("--set", dest="overrides", metavar="SECTION.KEY=VALUE", action="append", default=[],
                        help="override one configuration value (repeatable)")


def config_from_args(args: argparse.Namespace, env: Mapping[str, str] | None = None) -> Config:
    return load_config(getattr(args, "config", None), env=env, overrides=getattr(args, "overrides", []) or [])
