"""n-step targets on hand-computed sequences, with a termination and a truncation inside the window."""

import numpy as np
import pytest

from forcegrasp.nstep import NStepAccumulator
from forcegrasp.replay import Batch
from forcegrasp.sac import SAC, SACConfig

G = 0.9


def feed(acc, rewards, end):
    """States are 0, 1, 2, ...; step t goes t -> t+1 with rewards[t]; the last step ends as ``end``."""
    out = []
    for t, r in enumerate(rewards):
        last = t == len(rewards) - 1
        out += acc.push(t, t, r, t + 1, terminated=last and end == "terminated", truncated=last and end == "truncated")
    return out


def test_three_step_returns_inside_an_episode_and_at_a_termination():
    acc = NStepAccumulator(3, G)
    out = feed(acc, [1.0, 2.0, 3.0, 4.0, 5.0], "terminated")
    assert [t.obs for t in out] == [0, 1, 2, 3, 4]  # every step leaves exactly once, in order
    assert out[0].reward == pytest.approx(1 + G * 2 + G**2 * 3) and out[0].next_obs == 3 and out[0].horizon == 3
    assert out[1].reward == pytest.approx(2 + G * 3 + G**2 * 4) and out[1].next_obs == 4
    assert not out[0].terminated and not out[1].terminated
    # The window reaches the termination: the rest sum to the end and do not bootstrap.
    for t, want, h in ((out[2], 3 + G * 4 + G**2 * 5, 3), (out[3], 4 + G * 5, 2), (out[4], 5.0, 1)):
        assert t.reward == pytest.approx(want) and t.next_obs == 5 and t.terminated and t.horizon == h
    assert len(acc) == 0


def test_a_truncation_bootstraps_from_the_last_state_with_the_remaining_horizon():
    acc = NStepAccumulator(3, G)
    out = feed(acc, [1.0, 2.0, 3.0, 4.0], "truncated")
    assert [(t.obs, t.next_obs, t.horizon, t.terminated, t.truncated) for t in out] == [
        (0, 3, 3, False, False), (1, 4, 3, False, True), (2, 4, 2, False, True), (3, 4, 1, False, True)]
    assert out[2].reward == pytest.approx(3 + G * 4)


def test_short_episode_and_one_step_passthrough():
    out = feed(NStepAccumulator(3, G), [7.0], "terminated")
    assert len(out) == 1 and out[0].reward == 7.0 and out[0].horizon == 1 and out[0].terminated
    one = feed(NStepAccumulator(1, G), [1.0, 2.0], "truncated")
    assert [(t.reward, t.next_obs, t.horizon) for t in one] == [(1.0, 1, 1), (2.0, 2, 1)]
    with pytest.raises(ValueError):
        NStepAccumulator(0, G)


def test_learner_discounts_the_bootstrap_by_gamma_to_the_horizon():
    """The critic target is c r + gamma^h (1 - d) (min Q' - alpha log pi): check it for h = 1 and 3."""
    sac = SAC(3, 2, SACConfig(seed=0, gamma=G, reward_scale=0.5, hidden=(8, 8)))
    rng = np.random.default_rng(0)
    obs, nxt = rng.normal(size=(2, 3)).astype(np.float32), rng.normal(size=(2, 3)).astype(np.float32)
    batch = Batch(obs, np.zeros((2, 2), np.float32), np.array([1.0, 2.0], np.float32), nxt,
                  np.array([0.0, 1.0], np.float32), np.array([3.0, 1.0], np.float32))
    import torch

    t = sac._tensors(batch)
    gen_state = sac.target_generator.get_state()
    terms = sac.critic_terms(*t[:5], torch.tensor(0.0), discount=G ** t[5])
    sac.target_generator.set_state(gen_state)
    with torch.no_grad():
        a, _ = sac.actor.sample(t[3], sac.target_generator)
        q_next = sac.critic_target(t[3], a).amin(0)
    want = torch.tensor([0.5 * 1.0 + G**3 * q_next[0].item(), 0.5 * 2.0])
    assert torch.allclose(terms.target, want, atol=1e-5)
