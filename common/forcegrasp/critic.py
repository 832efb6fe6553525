"""The critic: twin Q-networks as one ensemble, built for the SAC update's speed."""

from __future__ import annotations

import math

import torch
from torch import nn


class TwinQ(nn.Module):
    """`n` independent Q-networks Q_i(s, a) evaluated together, as an ensemble.

    Layer k of every member is one slice of a ``(n, in, out)`` weight, so each layer of the whole
    ensemble is a single `baddbmm` instead of n small matmuls (and n optimizer parameter sets).
    The first layer is split into its observation and action parts, W1 [s; a] = W_s s + W_a a:
    the actor loss needs dQ/da only, so it evaluates `head` on a no-grad `embed` (the W_s s + b
    part) and back-propagates into the action columns alone.
    Initialisation matches `nn.Linear` (uniform in +-1/sqrt(fan_in)) so members start independent.

    ``layer_norm=True`` normalises every hidden pre-activation (Linear -> LayerNorm -> ReLU, with a
    per-member gain and shift), the critic regulariser of DroQ and RLPD that keeps Q-values bounded
    when targets are large (our +1000 success bonus) or updates are many per environment step.
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden=(256, 256), n: int = 2, layer_norm: bool = False):
        super().__init__()
        self.n = n
        self.layer_norm = bool(layer_norm)

        def uniform(fan_in, *shape):
            bound = 1.0 / math.sqrt(fan_in)
            return nn.Parameter(torch.empty(n, *shape).uniform_(-bound, bound))

        self.obs_weight = uniform(obs_dim + act_dim, obs_dim, hidden[0])
        self.act_weight = uniform(obs_dim + act_dim, act_dim, hidden[0])
        self.weights = nn.ParameterList()  # layers after the first
        self.biases = nn.ParameterList([uniform(obs_dim + act_dim, 1, hidden[0])])  # all layers
        dims = [*hidden, 1]
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            self.weights.append(uniform(d_in, d_in, d_out))
            self.biases.append(uniform(d_in, 1, d_out))
        # LayerNorm's affine part, one (gain, shift) per hidden layer and member.
        self.ln_gains = nn.ParameterList([nn.Parameter(torch.ones(n, 1, h)) for h in hidden] if layer_norm else [])
        self.ln_shifts = nn.ParameterList([nn.Parameter(torch.zeros(n, 1, h)) for h in hidden] if layer_norm else [])

    def embed(self, obs: torch.Tensor) -> torch.Tensor:
        """Observation part of every member's first layer (with its bias), ``(n, batch, hidden)``."""
        return torch.baddbmm(self.biases[0], obs.expand(self.n, -1, -1), self.obs_weight)

    def head(self, embedding: torch.Tensor, action: torch.Tensor, frozen: bool = False) -> torch.Tensor:
        """Q-values ``(n, batch)`` from `embed`'s output and the actions.

        ``frozen=True`` uses detached weights: gradients still flow to `action` (the actor loss
        needs dQ/da) but none are computed for, or accumulated into, the critic's weights.
        """
        own = (lambda t: t.detach()) if frozen else (lambda t: t)
        # ReLUs run in place on the fresh matmul outputs (baddbmm's backward does not need them),
        # saving a 2 x batch x hidden buffer and a pass over memory per layer.
        x = self._activate(torch.baddbmm(embedding, action.expand(self.n, -1, -1), own(self.act_weight)), 0, own)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases[1:])):
            x = torch.baddbmm(own(b), x, own(w))
            if i < last:
                x = self._activate(x, i + 1, own)
        return x.squeeze(-1)

    def _activate(self, x: torch.Tensor, layer: int, own) -> torch.Tensor:
        """ReLU of hidden layer `layer`'s pre-activation, layer-normalised first when enabled."""
        if self.layer_norm:
            x = torch.nn.functional.layer_norm(x, x.shape[-1:])
            x = torch.addcmul(own(self.ln_shifts[layer]), x, own(self.ln_gains[layer]))
        return x.relu_()

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.head(self.embed(obs), action)
