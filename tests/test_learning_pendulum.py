"""Proof that the SAC core learns: Pendulum-v1 swung up and balanced within a fixed budget.

A random policy scores about -1200 per episode and a good one about -150. Budget: 6,000
environment steps (1,000 random, then one update per step) with 64-unit networks and learning
rate 1e-3 (the usual Pendulum setting), one torch thread per gradient branch; about 40 s on a
2-core CPU. The learned policy is then saved, reloaded as a deployable `Policy` and evaluated
deterministically on held-out start states.
"""

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

from gymnasium.wrappers import RescaleAction  # noqa: E402

from forcegrasp.policy import Actor, Policy  # noqa: E402
from forcegrasp.replay import ReplayBuffer  # noqa: E402
from forcegrasp.sac import SAC, SACConfig  # noqa: E402


def pendulum():
    return RescaleAction(gym.make("Pendulum-v1"), np.float32(-1.0), np.float32(1.0))


def train(env, config: SACConfig | None = None, on_episode=None) -> SAC:
    """The textbook SAC loop around forcegrasp.sac.SAC on one Gymnasium env with a Box(-1, 1)
    action space: a check of the SAC core alone, with none of ForceGrasp's task or services."""
    cfg = config or SACConfig()
    space = env.action_space
    if not (np.allclose(space.low, -1.0) and np.allclose(space.high, 1.0)):
        raise ValueError(f"action space must be [-1, 1] (got {space}); wrap the env with RescaleAction(env, -1, 1)")
    obs_dim, act_dim = env.observation_space.shape[0], space.shape[0]
    sac = SAC(obs_dim, act_dim, cfg)
    buffer = ReplayBuffer(obs_dim, act_dim, min(cfg.buffer_size, cfg.total_steps))
    rng = np.random.default_rng(cfg.seed)

    obs, _ = env.reset(seed=cfg.seed)
    episode_return, updates_due = 0.0, 0.0
    for step in range(cfg.total_steps):
        if step < cfg.learning_starts:  # pure exploration fills the buffer first
            action = rng.uniform(-1.0, 1.0, act_dim).astype(np.float32)
        else:
            action = sac.act(obs)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        # Store the real next observation; only true termination stops bootstrapping.
        buffer.add(obs, action, reward, next_obs, float(terminated))
        episode_return += float(reward)
        obs = next_obs
        if terminated or truncated:
            if on_episode is not None:
                on_episode(step + 1, episode_return)
            obs, _ = env.reset()
            episode_return = 0.0

        if step + 1 >= cfg.learning_starts:  # fractional UTD ratios accumulate across steps
            updates_due += cfg.updates_per_step
            while updates_due >= 1.0:
                sac.update(buffer.sample(cfg.batch_size, rng), metrics=False)
                updates_due -= 1.0
    return sac


def evaluate(policy: Policy, episodes: int = 10) -> list[float]:
    env, returns = pendulum(), []
    for episode in range(episodes):
        obs, _ = env.reset(seed=10_000 + episode)  # held-out start states
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(policy(obs))
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    return returns


@pytest.mark.slow
def test_sac_solves_pendulum_within_budget(tmp_path):
    config = SACConfig(total_steps=6_000, learning_starts=1_000, hidden=(64, 64), batch_size=256,
                       actor_lr=1e-3, critic_lr=1e-3, alpha_lr=1e-3, seed=0, device="cpu", num_threads=1)
    episodes = []
    sac = train(pendulum(), config, on_episode=lambda step, ret: episodes.append(ret))

    untrained = evaluate(Policy.from_actor(Actor(3, 1, (64, 64)), sac.policy().metadata))
    sac.policy().save(tmp_path / "pendulum.policy")
    learned = evaluate(Policy.load(tmp_path / "pendulum.policy"))

    print(f"Pendulum-v1 after {config.total_steps} steps: evaluation return {np.mean(learned):.0f} "
          f"(untrained {np.mean(untrained):.0f}, first training episodes {np.mean(episodes[:5]):.0f})")
    assert len(episodes) == 30 and np.mean(episodes[:5]) < -800  # the random-action phase is bad
    assert np.mean(untrained) < -700
    assert np.mean(learned) > -300, f"mean evaluation return {np.mean(learned):.0f}: {np.round(learned)}"
    assert np.mean(episodes[-5:]) > -400  # training episodes improved too (with exploration noise)
