"""Soft Actor-Critic, the learner core (Haarnoja et al., 2018, "Soft Actor-Critic Algorithms and
Applications", arXiv:1812.05905): tanh-squashed Gaussian actor, twin Q critics with Polyak-averaged
targets, automatic entropy tuning.

Read top to bottom: the hyper-parameters, the `SAC` learner (one `update` is the paper's
Algorithm 1 inner loop), checkpoints. The critic ensemble is `forcegrasp.critic`; the actor
network lives in `forcegrasp.policy` because it is also what gets deployed; the named recipes
(`learner.recipe`) and their reading from the configuration are `forcegrasp.recipes`.

Update order: the three losses (critics, actor, temperature) are computed from the same
parameter values and applied together, as in the authors' original TensorFlow 1 code (softlearning
ran the Q, policy and temperature train ops in one ``session.run``); their later TF2 code,
stable-baselines3 and CleanRL step the critics before computing the actor loss. Computed from the
same parameters, the critic gradients and the actor/temperature gradients are independent, which
is most of why this is fast:

* on a CPU with two or more cores the two gradient computations run concurrently, each on its
  own thread (one OpenMP team each, no cross-core barriers inside a matmul);
* one fused Adam step over all parameter groups; one fused ``lerp`` for the Polyak update;
* both critics are one ensemble whose layers are single batched matmuls (weights ``(2, in, out)``);
* the actor loss sees the critics through detached weights, so its backward pass computes dQ/da
  but none of the critic weight gradients it would discard;
* metrics leave the device once per update, not once per value.
"""

from __future__ import annotations

import json
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import NamedTuple

import numpy as np
import safetensors.torch
import torch

from forcegrasp.policy import Actor, Policy, configure_threads, select_device, usable_cores
from forcegrasp.critic import TwinQ
from forcegrasp.normalization import RunningMeanStd
from forcegrasp.policy_file import PolicyMetadata, atomic_write
from forcegrasp.replay import Batch
from forcegrasp.sac_config import SACConfig  # noqa: F401  (part of this module's API)
from forcegrasp.task import TORQUES

CHECKPOINT_FORMAT = "forcegrasp-sac-checkpoint"
CHECKPOINT_VERSION = 1
METRICS = ("critic_loss", "actor_loss", "alpha_loss", "alpha", "entropy", "q1", "q2", "q_target")


class CriticTerms(NamedTuple):
    loss: torch.Tensor  # J_Q summed over both critics (gradient reaches the critics only)
    q: torch.Tensor  # (2, B) Q_i(s, a), detached
    target: torch.Tensor  # (B,) soft Bellman target y


class ActorTerms(NamedTuple):
    actor_loss: torch.Tensor  # J_pi (gradient reaches the actor only)
    alpha_loss: torch.Tensor  # J(alpha) (reaches log_alpha only; zero when alpha is fixed)
    log_prob: torch.Tensor  # (B,) log pi(a|s) of the fresh actions, detached


class SAC:
    """The learner: owns the actor, the critics, their targets, the optimizer and alpha.

    It does not own the replay buffer or the environment; callers pass minibatches to `update`.
    """

    def __init__(self, obs_dim: int, act_dim: int, config: SACConfig | None = None, priv_dim: int = 0):
        cfg = self.config = config or SACConfig()
        self.obs_dim, self.act_dim, self.priv_dim = int(obs_dim), int(act_dim), int(priv_dim)
        critic_in = self.obs_dim + self.priv_dim  # an asymmetric critic sees [obs, privileged]
        self.device = select_device(cfg.device)
        if self.device.type == "cpu":
            configure_threads(cfg.num_threads)

        critic_hidden = cfg.hidden if cfg.critic_hidden is None else cfg.critic_hidden
        with torch.random.fork_rng(devices=[]):  # seeded init without touching the global RNG
            torch.manual_seed(cfg.seed)
            actor = Actor(obs_dim, act_dim, cfg.hidden, cfg.log_std_bounds, obs_norm=cfg.obs_norm)
            critic = TwinQ(critic_in, act_dim, critic_hidden, layer_norm=cfg.critic_layer_norm)
        self.actor = actor.to(self.device)
        self.critic = critic.to(self.device)
        self.critic_target = TwinQ(critic_in, act_dim, critic_hidden, layer_norm=cfg.critic_layer_norm)
        self.critic_target = self.critic_target.to(self.device).requires_grad_(False)
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.log_alpha = torch.tensor(math.log(cfg.init_alpha), device=self.device, requires_grad=cfg.autotune_alpha)
        self.target_entropy = -float(act_dim) if cfg.target_entropy is None else float(cfg.target_entropy)

        # One Adam over three parameter groups: the losses touch disjoint parameters, so their
        # gradients can be computed separately and applied by a single (fused) step.
        groups = [{"params": list(self.critic.parameters()), "lr": cfg.critic_lr, "name": "critic"},
                  {"params": list(self.actor.parameters()), "lr": cfg.actor_lr, "name": "actor"}]
        if cfg.autotune_alpha:
            groups.append({"params": [self.log_alpha], "lr": cfg.alpha_lr, "name": "log_alpha"})
        adam = {"fused": True} if _fused_adam_ok(self.device) else {"foreach": True}
        self.optimizer = torch.optim.Adam(groups, **adam)
        self.critic_params = groups[0]["params"]
        self.target_params = list(self.critic_target.parameters())

        # Separate noise streams for the two gradient computations keep results identical
        # whether they run one after the other or concurrently.
        self.target_generator = torch.Generator(device=self.device).manual_seed(cfg.seed)
        self.policy_generator = torch.Generator(device=self.device).manual_seed(cfg.seed + 1)
        parallel = cfg.parallel_branches
        if parallel is None:
            parallel = self.device.type == "cpu" and usable_cores() >= 2
        self._worker = ThreadPoolExecutor(1, thread_name_prefix="sac-actor-grads") if parallel else None
        self.num_updates = 0
        self.obs_rms = RunningMeanStd(obs_dim) if cfg.obs_norm else None
        # Weight averaging: the policy handed out (weights, snapshots) is a slow average of the one
        # being trained, which damps the swings of successive snapshots.
        self.actor_avg = None
        if cfg.actor_ema > 0:
            self.actor_avg = Actor(obs_dim, act_dim, cfg.hidden, cfg.log_std_bounds, obs_norm=cfg.obs_norm)
            self.actor_avg = self.actor_avg.to(self.device).requires_grad_(False)
            self.actor_avg.load_state_dict(self.actor.state_dict())
            self._avg_params, self._live_params = list(self.actor_avg.parameters()), list(self.actor.parameters())

    @property
    def deployed_actor(self) -> Actor:
        """The actor that actors run and policy files hold: the average when ``actor_ema`` > 0."""
        if self.actor_avg is None:
            return self.actor
        if self.obs_rms is not None:  # same input statistics as the live actor
            self.actor_avg.obs_mean.copy_(self.actor.obs_mean)
            self.actor_avg.obs_std.copy_(self.actor.obs_std)
        return self.actor_avg

    def observe(self, obs: np.ndarray) -> None:
        """Fold new observations into the running statistics the actor (and critic) normalise with."""
        if self.obs_rms is None:
            return
        self.obs_rms.update(np.asarray(obs, dtype=np.float64).reshape(-1, self.obs_dim))
        with torch.no_grad():
            self.actor.obs_mean.copy_(torch.as_tensor(self.obs_rms.mean, dtype=torch.float32))
            self.actor.obs_std.copy_(torch.as_tensor(self.obs_rms.std(), dtype=torch.float32))

    @property
    def alpha(self) -> float:
        return float(self.log_alpha.detach().exp())

    # -- the gradient step ----------------------------------------------------------------------
    def critic_terms(self, obs, action, reward, next_obs, terminated, alpha, discount=None, critic_obs=None,
                     next_critic_obs=None) -> CriticTerms:
        """Critic objective on one minibatch of tensors; `alpha` is the (detached) temperature.

        ``discount`` is gamma^h per transition (n-step returns; default gamma); ``critic_obs`` and
        ``next_critic_obs`` are what the critic sees when it differs from the actor's observation
        (an asymmetric critic: [obs, privileged]).
        """
        critic_obs = obs if critic_obs is None else critic_obs
        next_critic_obs = next_obs if next_critic_obs is None else next_critic_obs
        discount = self.config.gamma if discount is None else discount
        # Soft Bellman target with the smaller target Q (clipped double-Q) and a fresh action:
        # y = c r + gamma^h (1 - done) (min_i Q'_i(s', a') - alpha log pi(a'|s')),  a' ~ pi(.|s').
        with torch.no_grad():
            next_action, next_log_prob = self.actor.sample(next_obs, self.target_generator)
            next_q = self.critic_target(next_critic_obs, next_action).amin(0)
            target = self.config.reward_scale * reward + discount * (1.0 - terminated) * (
                next_q - alpha * next_log_prob)
        # J_Q = 0.5 E[(Q_i(s, a) - y)^2], summed over both critics.
        q = self.critic(critic_obs, action)  # (2, B)
        loss = 0.5 * (q - target).square().mean(1).sum()
        return CriticTerms(loss, q.detach(), target)

    def actor_terms(self, obs, alpha, critic_obs=None) -> ActorTerms:
        """Actor and temperature objectives on one minibatch of observations."""
        # J_pi = E[alpha log pi(a|s) - min_i Q_i(s, a)], a = tanh(mean + std eps) reparameterised.
        # The critics are frozen (detached weights): they pass dQ/da to the actor and take no
        # gradient; starting from a no-grad observation embedding, only the 7 action columns of
        # their first layer are back-propagated.
        new_action, log_prob = self.actor.sample(obs, self.policy_generator)
        with torch.no_grad():
            embedding = self.critic.embed(obs if critic_obs is None else critic_obs)
        q_new = self.critic.head(embedding, new_action, frozen=True).amin(0)
        actor_loss = (alpha * log_prob - q_new).mean()
        # J(alpha) = E[-alpha (log pi(a|s) + target_entropy)]: raises alpha while the policy's
        # entropy is below the target and lowers it above.
        log_prob = log_prob.detach()
        if self.config.autotune_alpha:
            alpha_loss = -(self.log_alpha.exp() * (log_prob + self.target_entropy)).mean()
        else:
            alpha_loss = torch.zeros((), device=self.device)
        return ActorTerms(actor_loss, alpha_loss, log_prob)

    def _noisy_torques(self, obs: torch.Tensor) -> torch.Tensor:
        """``obs`` with ``actor_torque_noise`` on its torques (forcegrasp.task.TORQUES), a sigma drawn
        per sample: what the actor's loss sees (the observations themselves stay as collected)."""
        top = self.config.actor_torque_noise
        if not top:
            return obs
        n, g = len(obs), self.policy_generator
        sigma = torch.rand(n, 1, generator=g, device=obs.device) * top
        noisy = obs.clone()
        noisy[:, TORQUES] += sigma * torch.randn(n, TORQUES.stop - TORQUES.start, generator=g, device=obs.device)
        return noisy

    def update(self, batch, metrics: bool = True) -> dict[str, float]:
        """One gradient step on critics, actor and temperature, then the target-critic update.

        `batch` is a `forcegrasp.replay.Batch` (or a dict with its fields) of arrays or tensors.
        Returns float metrics; ``metrics=False`` skips their (single) device-to-host copy.
        """
        obs, action, reward, next_obs, terminated, horizon, priv, next_priv = self._tensors(batch)
        discount = None if horizon is None else self.config.gamma ** horizon
        critic_obs = next_critic_obs = None
        if self.obs_rms is not None:  # the critic sees what the actor's first layer sees
            critic_obs, next_critic_obs = self.actor.normalize(obs), self.actor.normalize(next_obs)
        if self.priv_dim:
            if priv is None or next_priv is None:
                raise ValueError(f"this learner's critic needs {self.priv_dim} privileged values per transition")
            critic_obs = torch.cat([obs if critic_obs is None else critic_obs, priv], 1)
            next_critic_obs = torch.cat([next_obs if next_critic_obs is None else next_critic_obs, next_priv], 1)
        alpha = self.log_alpha.detach().exp()
        threads = torch.get_num_threads()

        def critic_grads() -> CriticTerms:
            terms = self.critic_terms(obs, action, reward, next_obs, terminated, alpha, discount, critic_obs,
                                      next_critic_obs)
            terms.loss.backward()
            return terms

        def actor_grads() -> ActorTerms:
            if torch.get_num_threads() != threads:  # a worker thread keeps the count it started with
                torch.set_num_threads(threads)
            terms = self.actor_terms(self._noisy_torques(obs), alpha, obs if critic_obs is None else critic_obs)
            (terms.actor_loss + terms.alpha_loss).backward()
            return terms

        # The two gradient computations read the same parameters and write disjoint .grad
        # fields, so on a multi-core CPU they run concurrently (torch releases the GIL in ops).
        self.optimizer.zero_grad(set_to_none=True)
        if self._worker is None:
            critic, actor = critic_grads(), actor_grads()
        else:
            pending = self._worker.submit(actor_grads)
            try:
                critic = critic_grads()
            finally:
                actor = pending.result()  # always wait: the worker must not outlive this update
        self.optimizer.step()

        # Target critics: theta' <- theta' + tau (theta - theta'), one fused op over all tensors.
        self.num_updates += 1
        if self.num_updates % self.config.target_update_interval == 0:
            with torch.no_grad():
                torch._foreach_lerp_(self.target_params, self.critic_params, self.config.tau)
        if self.actor_avg is not None:
            with torch.no_grad():
                torch._foreach_lerp_(self._avg_params, self._live_params, self.config.actor_ema)

        if not metrics:
            return {}
        values = torch.stack([
            critic.loss.detach(), actor.actor_loss.detach(), actor.alpha_loss.detach(), alpha,
            -actor.log_prob.mean(), critic.q[0].mean(), critic.q[1].mean(), critic.target.mean(),
        ]).tolist()  # the only device-to-host transfer of the step
        return dict(zip(METRICS, values))

    def _tensors(self, batch):
        if isinstance(batch, dict):
            batch = Batch(**batch)
        return tuple(
            None if getattr(batch, k) is None else
            torch.as_tensor(getattr(batch, k)).to(self.device, torch.float32, non_blocking=True)
            for k in ("obs", "action", "reward", "next_obs", "terminated", "horizon", "privileged", "next_privileged")
        )

    # -- acting ---------------------------------------------------------------------------------
    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """Action(s) in [-1, 1] for one observation or a batch, for local data collection."""
        obs = np.asarray(obs, dtype=np.float32)
        with torch.inference_mode():
            x = torch.as_tensor(obs, device=self.device)
            x = x if x.ndim == 2 else x.unsqueeze(0)
            a = self.actor.deterministic(x) if deterministic else self.actor.sample(x, self.policy_generator)[0]
            a = a.cpu().numpy()
        return a if obs.ndim == 2 else a[0]

    def policy(self, metadata: PolicyMetadata | None = None, device="cpu") -> Policy:
        """A standalone copy of the current actor, ready to save or deploy."""
        if metadata is None:  # unscaled: actions in [-1, 1] are the env's own units
            metadata = PolicyMetadata([("obs", self.obs_dim)], [("action", self.act_dim)], self.config.hidden,
                                      training_steps=self.num_updates, obs_norm=self.config.obs_norm,
                                      action_low=[-1.0] * self.act_dim, action_high=[1.0] * self.act_dim)
        return Policy.from_actor(self.deployed_actor, metadata, device=device)

    # -- checkpoints ----------------------------------------------------------------------------
    def state_dict(self) -> dict[str, torch.Tensor]:
        """Everything needed to resume exactly, as a flat ``{name: tensor}`` dict.

        Networks, targets, log-alpha, the update counter, both sampling RNG states, and each Adam
        parameter's step count and moments (zeros before the first step, which is what Adam starts
        from). Adam's hyper-parameters come from the config, so they are not repeated here.
        """
        state = {"log_alpha": self.log_alpha.detach(), "num_updates": torch.tensor(self.num_updates, dtype=torch.int64),
                 "target_generator": self.target_generator.get_state(),
                 "policy_generator": self.policy_generator.get_state()}
        for prefix, module in self._modules():
            state.update({f"{prefix}.{k}": v for k, v in module.state_dict().items()})
        if self.obs_rms is not None:
            state.update({f"obs_rms.{k}": torch.as_tensor(v) for k, v in self.obs_rms.state().items()})
        saved = self.optimizer.state_dict()["state"]
        for idx, p in enumerate(p for g in self.optimizer.param_groups for p in g["params"]):
            slots = saved.get(idx) or {"step": torch.zeros((), dtype=torch.float32), "exp_avg": torch.zeros_like(p),
                                       "exp_avg_sq": torch.zeros_like(p)}
            state.update({f"adam.{idx}.{k}": torch.as_tensor(v) for k, v in slots.items()})
        return {k: v.detach().contiguous() for k, v in state.items()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Inverse of `state_dict`; raises `ValueError` naming any missing, extra or misshapen entry."""
        expected = {k: tuple(v.shape) for k, v in self.state_dict().items()}
        missing, unexpected = sorted(set(expected) - set(state)), sorted(set(state) - set(expected))
        if missing or unexpected:
            raise ValueError(f"SAC state does not match this learner: missing {missing}, unexpected {unexpected}")
        for k, v in state.items():
            if tuple(v.shape) != expected[k] and not k.endswith("_generator"):
                raise ValueError(f"SAC state entry {k!r} has shape {tuple(v.shape)}, expected {expected[k]}")
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.num_updates = int(state["num_updates"])
        if self.obs_rms is not None:
            self.obs_rms.load({k: state[f"obs_rms.{k}"].numpy() for k in ("count", "mean", "var")})
        for offset, name in enumerate(("target_generator", "policy_generator")):
            if tuple(state[name].shape) == expected[name]:
                getattr(self, name).set_state(state[name].cpu())
            else:  # saved on another device type (CPU and CUDA generators differ): fresh stream
                getattr(self, name).manual_seed(self.config.seed + offset + 2 * self.num_updates)
        for prefix, module in self._modules():
            module.load_state_dict({k[len(prefix) + 1 :]: v for k, v in state.items() if k.startswith(prefix + ".")})
        slots: dict[int, dict] = {}
        for k, v in state.items():
            if k.startswith("adam."):
                _, idx, name = k.split(".")
                slots.setdefault(int(idx), {})[name] = v
        self.optimizer.load_state_dict({"state": slots, "param_groups": self.optimizer.state_dict()["param_groups"]})

    def _modules(self):
        modules = (("actor", self.actor), ("critic", self.critic), ("critic_target", self.critic_target))
        return modules + ((("actor_avg", self.actor_avg),) if self.actor_avg is not None else ())

    def save_checkpoint(self, path: str | os.PathLike, extra: dict | None = None) -> Path:
        """Atomic safetensors file: the tensors of `state_dict`, config and `extra` as header JSON."""
        header = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "obs_dim": self.obs_dim,
                  "act_dim": self.act_dim, "priv_dim": self.priv_dim, "config": asdict(self.config),
                  "extra": extra or {}}
        data = safetensors.torch.save({k: v.cpu() for k, v in self.state_dict().items()},
                                      metadata={"forcegrasp.sac": json.dumps(header)})
        with atomic_write(path) as f:
            f.write(data)
        return Path(path)

    @classmethod
    def load_checkpoint(cls, path: str | os.PathLike, device: str | None = None) -> tuple["SAC", dict]:
        """Rebuild a learner from `save_checkpoint`; returns ``(sac, extra)``. Never unpickles."""
        try:
            with safetensors.safe_open(str(path), framework="pt") as f:
                header = json.loads((f.metadata() or {})["forcegrasp.sac"])
                state = {k: f.get_tensor(k) for k in f.keys()}
        except (KeyError, json.JSONDecodeError, safetensors.SafetensorError) as exc:
            raise ValueError(f"{path}: not a readable SAC checkpoint ({type(exc).__name__}: {exc})") from None
        if header.get("format") != CHECKPOINT_FORMAT or header.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"{path}: unsupported checkpoint format {header.get('format')!r} v{header.get('version')!r}")
        known = {f.name for f in fields(SACConfig)}
        config = SACConfig(**{k: v for k, v in header["config"].items() if k in known})
        if device is not None:
            config.device = device
        sac = cls(header["obs_dim"], header["act_dim"], config, priv_dim=int(header.get("priv_dim", 0)))
        sac.load_state_dict(state)
        return sac, header["extra"]


def _fused_adam_ok(device: torch.device) -> bool:
    """Fused Adam runs the whole parameter update as one kernel; CPU support arrived in torch 2.4."""
    try:
        torch.optim.Adam([torch.zeros(1, device=device, requires_grad=True)], fused=True)
        return True
    except (RuntimeError, TypeError):
        return False
