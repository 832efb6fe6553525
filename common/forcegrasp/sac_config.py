"""SAC's hyper-parameters, torch-free: the configuration checks every [learner.sac] key and value
before any service starts, without importing the learner's numerical stack."""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass

@dataclass
class SACConfig:
    """Every SAC hyper-parameter; defaults are the paper's (table 1 and section 7)."""

    # Data collection and run length.
    total_steps: int = 1_000_000  # environment steps
    learning_starts: int = 1_000  # uniformly random actions before the first update
    updates_per_step: float = 1.0  # gradient updates per environment step (UTD ratio)
    buffer_size: int = 1_000_000  # replay capacity (transitions)
    batch_size: int = 256
    # Networks.
    hidden: tuple[int, ...] = (256, 256)  # actor and each critic, ReLU
    critic_hidden: tuple[int, ...] | None = None  # each critic's hidden sizes; None: `hidden`
    critic_layer_norm: bool = False  # LayerNorm before every critic ReLU (DroQ / RLPD)
    log_std_bounds: tuple[float, float] = (-20.0, 2.0)  # clamp of the actor's log-std
    # Optimisation (Adam).
    actor_lr: float = 3e-4
    critic_lr: float = 3e-4
    alpha_lr: float = 3e-4
    gamma: float = 0.99  # discount
    reward_scale: float = 1.0  # rewards are multiplied by this in the critic targets (Q-value scale)
    n_step: int = 1  # n-step returns, built by the actors (forcegrasp.nstep); bootstrap with gamma^h
    privileged_critic: bool = False  # asymmetric critic: also sees simulator state the actor never does
    obs_norm: bool = False  # running mean/std of observations, frozen into every policy file
    actor_ema: float = 0.0  # >0: actors and policy files get a Polyak average of the actor at this rate
    # >0: the actor's loss sees each sample's torques (obs[0:24]) with Gaussian noise of sigma ~ U(0, this)
    # N*m added, the critics see them clean: robustness to torque noise learnt without noisy episodes.
    actor_torque_noise: float = 0.0
    tau: float = 0.005  # Polyak rate of the target critics
    target_update_interval: int = 1  # updates between target-critic updates
    # Entropy temperature.
    autotune_alpha: bool = True  # learn alpha so that entropy tracks target_entropy
    init_alpha: float = 1.0
    target_entropy: float | None = None  # None: -action_dim (paper's heuristic)
    # Runtime.
    seed: int = 0
    device: str = "auto"  # "auto": CUDA when available, else CPU
    num_threads: int | None = None  # CPU intra-op threads; None: half the usable cores (configure_threads)
    parallel_branches: bool | None = None  # critic and actor gradients in two threads; None: CPU, >= 2 cores

    def __post_init__(self):
        self.hidden = tuple(int(h) for h in self.hidden)
        if self.critic_hidden is not None:
            self.critic_hidden = tuple(int(h) for h in self.critic_hidden)
        for name in ("hidden", "critic_hidden"):
            sizes = getattr(self, name)
            if sizes is not None and (not sizes or min(sizes) <= 0):
                raise ValueError(f"{name} {sizes}: at least one layer, every size positive")
        self.log_std_bounds = tuple(float(b) for b in self.log_std_bounds)


#: Numeric settings with bounds beyond their type: (low, high, low inclusive).
_BOUNDS = {"total_steps": (1, None), "learning_starts": (0, None), "updates_per_step": (0, None, False),
           "buffer_size": (1, None), "batch_size": (1, None), "actor_lr": (0, None, False),
           "critic_lr": (0, None, False), "alpha_lr": (0, None, False), "gamma": (0, 1, False),
           "reward_scale": (0, None, False), "n_step": (1, None), "actor_ema": (0, 1), "actor_torque_noise": (0, None),
           "tau": (0, 1, False), "target_update_interval": (1, None), "init_alpha": (0, None, False),
           "num_threads": (1, None)}


def check_value(name: str, value):
    """``value`` as SACConfig field ``name`` takes it (lists as tuples, ints as floats where a float
    is wanted), or ValueError saying what is allowed."""
    fields = {f.name: f for f in dataclasses.fields(SACConfig)}
    if name not in fields:
        raise ValueError(f"unknown SAC setting {name!r}; known: {', '.join(sorted(fields))}")
    hint = typing.get_type_hints(SACConfig)[name]
    options = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, type(int | None)) else (hint,)
    for option in options:
        ok, coerced = _as(value, option)
        if ok:
            break
    else:
        want = " or ".join(_describe(o) for o in options)
        raise ValueError(f"{name} = {value!r} is not {want}")
    if name in _BOUNDS and coerced is not None:
        low, high, *inclusive = _BOUNDS[name]
        low_ok = coerced >= low if (inclusive[0] if inclusive else True) else coerced > low
        if not low_ok or (high is not None and coerced > high):
            bound = ("> " if inclusive and not inclusive[0] else ">= ") + str(low) + (f" and <= {high}" if high is not None else "")
            raise ValueError(f"{name} = {value!r} must be {bound}")
    return coerced


def _as(value, option) -> tuple[bool, object]:
    if option is type(None):
        return value is None, None
    if option is bool:
        return isinstance(value, bool), value
    if option is int:
        return isinstance(value, int) and not isinstance(value, bool), value
    if option is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool), float(value) if isinstance(value, (int, float)) else value
    if option is str:
        return isinstance(value, str), value
    if typing.get_origin(option) is tuple:
        args = typing.get_args(option)
        if not isinstance(value, (list, tuple)):
            return False, value
        items = list(value)
        kinds = [args[0]] * len(items) if len(args) == 2 and args[1] is Ellipsis else list(args)
        if len(kinds) != len(items):
            return False, value
        out = []
        for item, kind in zip(items, kinds):
            ok, item = _as(item, kind)
            if not ok:
                return False, value
            out.append(item)
        return True, tuple(out)
    return False, value


def _describe(option) -> str:
    if option is type(None):
        return "none"
    if typing.get_origin(option) is tuple:
        args = typing.get_args(option)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {args[0].__name__}"
        return f"a list of {len(args)} numbers"
    return {bool: "true/false", int: "a whole number", float: "a number", str: "a string"}.get(option, str(option))
