"""The deployable policy: the SAC actor network and a numpy-in, numpy-out wrapper around it.

This module holds everything an actor process, the evaluator or a user needs to *run* a trained
policy, and nothing the learner alone needs (no critics, no optimizers, no replay). The learner
(`forcegrasp.sac`) imports `Actor` from here, so the network that is trained is, by construction,
the network that is deployed.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from forcegrasp.policy_file import (
    PolicyFileError,
    PolicyMetadata,
    actor_param_shapes,
    load_policy_bytes,
    load_policy_file,
    policy_to_bytes,
    save_policy_file,
)

LOG_2PI = math.log(2.0 * math.pi)
LOG_2 = math.log(2.0)


def select_device(device: str | torch.device = "auto") -> torch.device:
    """`"auto"` picks CUDA when present and the CPU otherwise; anything else is taken as given."""
    if str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask, e.g. a container's CPU set)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def configure_threads(num_threads: int | None = None) -> int:
    """Set torch's intra-op threads (default: half the usable cores, at least 1, at most 8) and
    one inter-op thread; returns the count in effect.

    Half, because the learner computes its critic and actor gradients on two threads at once,
    each with its own team of this size. Not all cores in one team, because torch's OpenMP
    threads wait for each other at the end of every op: when another busy process (environment,
    actors, network stack) shares the cores, each op waits for a descheduled thread. On a loaded
    2-core machine that made SAC updates 20-40x slower with one 2-thread team, while two
    independent 1-thread branches kept their pace.
    """
    if num_threads is None:
        num_threads = min(max(usable_cores() // 2, 1), 8)
    torch.set_num_threads(max(1, int(num_threads)))
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # only settable before the first inter-op parallel work; harmless to skip
        pass
    return torch.get_num_threads()


OBS_CLIP = 10.0  # normalised observations are clipped to +-this (a value never seen in training)


class Actor(nn.Module):
    """Tanh-squashed Gaussian policy: an MLP gives the mean and log-std of u, and a = tanh(u).

    Parameters are named ``layers.{i}.weight/bias``; the last layer outputs ``2 * act_dim`` values
    (mean, then log-std). `forcegrasp.policy_file.actor_param_shapes` relies on this naming.
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden=(256, 256), log_std_bounds=(-20.0, 2.0),
                 obs_norm: bool = False):
        super().__init__()
        dims = [obs_dim, *hidden, 2 * act_dim]
        self.layers = nn.ModuleList(nn.Linear(i, o) for i, o in zip(dims[:-1], dims[1:]))
        self.obs_dim, self.act_dim, self.hidden = obs_dim, act_dim, tuple(hidden)
        self.log_std_min, self.log_std_max = (float(b) for b in log_std_bounds)
        self.obs_norm = bool(obs_norm)
        if self.obs_norm:  # part of the state dict, so of every policy file and weights message
            self.register_buffer("obs_mean", torch.zeros(obs_dim))
            self.register_buffer("obs_std", torch.ones(obs_dim))

    def normalize(self, obs: torch.Tensor) -> torch.Tensor:
        """(obs - mean) / std clipped to +-OBS_CLIP with the frozen statistics; identity without."""
        if not self.obs_norm:
            return obs
        return ((obs - self.obs_mean) / self.obs_std).clamp(-OBS_CLIP, OBS_CLIP)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and (clamped) log-std of the pre-squash Gaussian."""
        x = self.normalize(obs)
        for layer in self.layers[:-1]:
            x = F.relu(layer(x), inplace=True)  # in place on the fresh matmul output: less memory traffic
        mean, log_std = self.layers[-1](x).chunk(2, dim=-1)
        return mean, log_std.clamp(self.log_std_min, self.log_std_max)

    def sample(self, obs: torch.Tensor, generator: torch.Generator | None = None):
        """Reparameterised sample a = tanh(mean + std * eps) and its log-probability log pi(a|s).

        log pi(a) = log N(u; mean, std) - sum log(1 - tanh(u)^2)   (change of variables, paper app. C)
        with log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), which stays finite where tanh saturates.
        """
        mean, log_std = self(obs)
        eps = torch.randn(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype)
        u = mean + log_std.exp() * eps
        log_prob = (-0.5 * eps.square() - log_std - 0.5 * LOG_2PI).sum(-1)
        log_prob = log_prob - (2.0 * (LOG_2 - u - F.softplus(-2.0 * u))).sum(-1)
        return torch.tanh(u), log_prob

    def deterministic(self, obs: torch.Tensor) -> torch.Tensor:
        """The action the evaluator and users run: tanh of the mean."""
        return torch.tanh(self(obs)[0])


class Policy:
    """A trained actor that maps numpy observations to actions in [-1, 1]; inference only.

    >>> policy = Policy.load("grasp.policy")
    >>> action = policy(obs)                        # obs (77,) -> (7,), deterministic
    >>> actions = policy(obs_batch, deterministic=False)  # (n, 77) -> (n, 7), sampled
    """

    def __init__(self, actor: Actor, metadata: PolicyMetadata, device="cpu", seed: int | None = None):
        self.device = select_device(device)
        self.actor = actor.to(self.device).eval().requires_grad_(False)
        self.metadata = metadata
        seed = seed if seed is not None else int(np.random.SeedSequence().entropy % 2**63)
        self._generator = torch.Generator(device=self.device)
        self._generator.manual_seed(seed)
        # On the CPU the same network runs in numpy: for the small batches actors and the
        # evaluator pass, torch's per-op dispatch costs 3-4x the arithmetic (~0.45 vs ~0.12 ms
        # for 8 observations here). Both paths compute the same function (tests/test_policy_file.py).
        self._rng = np.random.default_rng(seed)
        self._numpy_layers = None
        if self.device.type == "cpu":
            self._numpy_layers = [
                (layer.weight.detach().numpy().T.copy(), layer.bias.detach().numpy().copy()) for layer in self.actor.layers
            ]
            self._numpy_norm = None
            if self.actor.obs_norm:
                self._numpy_norm = (self.actor.obs_mean.numpy().copy(), 1.0 / self.actor.obs_std.numpy())

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def from_weights(cls, weights: dict[str, np.ndarray], metadata: PolicyMetadata, device="cpu", seed=None):
        """Build from a flat ``{name: array}`` dict (as shipped over the network) and its metadata."""
        expected = actor_param_shapes(metadata)
        if set(weights) != set(expected):
            raise PolicyFileError(
                f"weights do not match the metadata: missing {sorted(set(expected) - set(weights))}, "
                f"unexpected {sorted(set(weights) - set(expected))}"
            )
        for name, shape in expected.items():
            if tuple(np.shape(weights[name])) != shape:
                raise PolicyFileError(f"weight {name!r} has shape {tuple(np.shape(weights[name]))}, expected {shape}")
        if metadata.obs_norm and not np.all(np.asarray(weights["obs_std"]) > 0):
            raise PolicyFileError("obs_std must be positive everywhere")
        actor = Actor(metadata.obs_dim, metadata.act_dim, metadata.hidden, metadata.log_std_bounds, metadata.obs_norm)
        actor.load_state_dict({k: torch.tensor(np.asarray(v, dtype=np.float32)) for k, v in weights.items()})
        return cls(actor, metadata, device=device, seed=seed)

    @classmethod
    def from_actor(cls, actor: Actor, metadata: PolicyMetadata, device="cpu", seed=None):
        """Copy a (learner's) actor into a standalone policy; later training does not affect it."""
        return cls.from_weights(weights_of(actor), metadata, device=device, seed=seed)

    @classmethod
    def load(cls, path: str | os.PathLike, device="cpu", seed=None) -> "Policy":
        weights, metadata = load_policy_file(path)
        return cls.from_weights(weights, metadata, device=device, seed=seed)

    @classmethod
    def from_bytes(cls, data: bytes, device="cpu", seed=None) -> "Policy":
        weights, metadata = load_policy_bytes(data)
        return cls.from_weights(weights, metadata, device=device, seed=seed)

    # -- export -------------------------------------------------------------------------------
    def weights(self) -> dict[str, np.ndarray]:
        """Flat ``{name: float32 array}`` copy of the actor weights (what the network layer ships)."""
        return weights_of(self.actor)

    def save(self, path: str | os.PathLike) -> Path:
        return save_policy_file(path, self.weights(), self.metadata)

    def to_bytes(self) -> bytes:
        """The policy file's bytes, for sending without touching the disk."""
        return policy_to_bytes(self.weights(), self.metadata)

    # -- inference ----------------------------------------------------------------------------
    def __call__(self, obs, deterministic: bool = True) -> np.ndarray:
        """Action(s) in [-1, 1] for one observation ``(obs_dim,)`` or a batch ``(n, obs_dim)``."""
        obs = np.asarray(obs)
        if obs.ndim not in (1, 2) or obs.shape[-1] != self.metadata.obs_dim:
            raise ValueError(
                f"observation has shape {obs.shape}; this policy expects ({self.metadata.obs_dim},) "
                f"or (n, {self.metadata.obs_dim})"
            )
        if not np.issubdtype(obs.dtype, np.number) or np.issubdtype(obs.dtype, np.complexfloating):
            raise ValueError(f"observation has dtype {obs.dtype}; expected real numbers")
        if not np.all(np.isfinite(obs)):
            bad = np.argwhere(~np.isfinite(obs))[:5].tolist()
            raise ValueError(f"observation contains NaN or inf (at indices {bad})")
        if self._numpy_layers is not None:
            action = self._numpy_action(np.atleast_2d(obs).astype(np.float32, copy=False), deterministic)
            return action if obs.ndim == 2 else action[0]
        with torch.inference_mode():
            x = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            batch = x if x.ndim == 2 else x.unsqueeze(0)
            if deterministic:
                action = self.actor.deterministic(batch)
            else:
                action = self.actor.sample(batch, generator=self._generator)[0]
            action = action.cpu().numpy()
        return action if obs.ndim == 2 else action[0]

    def _numpy_action(self, x: np.ndarray, deterministic: bool) -> np.ndarray:
        """`Actor.deterministic` / `Actor.sample`'s action, in numpy (no log-probability needed)."""
        *hidden, (w_out, b_out) = self._numpy_layers
        if self._numpy_norm is not None:
            mean, inv_std = self._numpy_norm
            x = np.clip((x - mean) * inv_std, -OBS_CLIP, OBS_CLIP)
        for w, b in hidden:
            x = np.maximum(x @ w + b, 0.0)
        out = x @ w_out + b_out
        act_dim = self.metadata.act_dim
        mean = out[:, :act_dim]
        if deterministic:
            return np.tanh(mean)
        log_std = np.clip(out[:, act_dim:], self.actor.log_std_min, self.actor.log_std_max)
        return np.tanh(mean + np.exp(log_std) * self._rng.standard_normal(mean.shape, dtype=np.float32))

    def rescale(self, action: np.ndarray) -> np.ndarray:
        """Map [-1, 1] actions to the environment's units recorded in the metadata (low/high)."""
        low, high = self.metadata.action_low, self.metadata.action_high
        if low is None or high is None:
            return np.asarray(action)
        low, high = np.asarray(low, np.float32), np.asarray(high, np.float32)
        return low + (np.asarray(action) + 1.0) * 0.5 * (high - low)


def weights_of(actor: Actor) -> dict[str, np.ndarray]:
    """Flat numpy copy of an actor's parameters, detached from any device or autograd graph."""
    return {k: v.detach().to("cpu", torch.float32).numpy().copy() for k, v in actor.state_dict().items()}
