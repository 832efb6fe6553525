"""SAC core: losses against independent computations, target update, gradient routing, resuming."""

import math
import pickle

import numpy as np
import pytest
import safetensors
import torch

from forcegrasp.policy import Actor, select_device
from forcegrasp.replay import Batch
from forcegrasp.critic import TwinQ
from forcegrasp.sac import METRICS, SAC, SACConfig

OBS, ACT, B = 3, 2, 5


def tiny_sac(**overrides) -> SAC:
    cfg = dict(hidden=(4, 4), device="cpu", num_threads=1, seed=3, init_alpha=0.7, gamma=0.9, tau=0.1)
    cfg.update(overrides)
    return SAC(OBS, ACT, SACConfig(**cfg))


def random_batch(seed=0, n=B, obs=OBS, act=ACT) -> Batch:
    rng = np.random.default_rng(seed)
    return Batch(rng.standard_normal((n, obs)).astype(np.float32), rng.uniform(-1, 1, (n, act)).astype(np.float32),
                 rng.standard_normal(n).astype(np.float32), rng.standard_normal((n, obs)).astype(np.float32),
                 np.array([0, 1, 0, 0, 1][:n] + [0] * max(0, n - 5), np.float32))


def upcoming_noise(generator: torch.Generator, shape):
    """The Gaussian noise `generator` will produce next, drawn from a copy of it."""
    g = torch.Generator()
    g.set_state(generator.get_state())
    return torch.randn(shape, generator=g).double().numpy()


# -- independent float64 numpy reference ----------------------------------------------------------
def np_mlp(x, weights, biases):
    for i, (w, b) in enumerate(zip(weights, biases)):
        x = x @ w + b
        if i < len(weights) - 1:
            x = np.maximum(x, 0.0)
    return x


def np_actor(actor: Actor, obs, eps):
    ws = [l.weight.detach().double().numpy().T for l in actor.layers]
    bs = [l.bias.detach().double().numpy() for l in actor.layers]
    out = np_mlp(obs.astype(np.float64), ws, bs)
    mean, log_std = out[:, :ACT], np.clip(out[:, ACT:], actor.log_std_min, actor.log_std_max)
    u = mean + np.exp(log_std) * eps
    a = np.tanh(u)
    gauss = -0.5 * eps**2 - log_std - 0.5 * np.log(2 * np.pi)
    return a, (gauss - np.log(1 - np.tanh(u) ** 2)).sum(1)


def np_critics(critic: TwinQ, obs, act):
    x = np.concatenate([obs, act], 1).astype(np.float64)
    first = torch.cat([critic.obs_weight, critic.act_weight], 1)  # W1 acting on [s; a]
    return np.stack([
        np_mlp(x, [w[i].detach().double().numpy() for w in [first, *critic.weights]],
               [b[i, 0].detach().double().numpy() for b in critic.biases])[:, 0]
        for i in range(2)
    ])


def tensors(batch: Batch):
    return [torch.as_tensor(getattr(batch, k)) for k in ("obs", "action", "reward", "next_obs", "terminated")]


def test_losses_match_an_independent_float64_computation():
    sac = tiny_sac()
    batch = random_batch()
    with torch.no_grad():  # make target and online critics differ, as they do during training
        for p in sac.critic_target.parameters():
            p.add_(0.3 * torch.randn_like(p))
    eps_next = upcoming_noise(sac.target_generator, (B, ACT))
    eps_new = upcoming_noise(sac.policy_generator, (B, ACT))
    alpha_t = sac.log_alpha.detach().exp()
    critic = sac.critic_terms(*tensors(batch), alpha_t)
    actor = sac.actor_terms(torch.as_tensor(batch.obs), alpha_t)

    alpha, gamma = 0.7, 0.9
    next_a, next_logp = np_actor(sac.actor, batch.next_obs, eps_next)
    next_q = np_critics(sac.critic_target, batch.next_obs, next_a).min(0)
    y = batch.reward + gamma * (1 - batch.terminated) * (next_q - alpha * next_logp)
    q = np_critics(sac.critic, batch.obs, batch.action)
    critic_loss = 0.5 * ((q - y) ** 2).mean(1).sum()
    new_a, logp = np_actor(sac.actor, batch.obs, eps_new)
    actor_loss = (alpha * logp - np_critics(sac.critic, batch.obs, new_a).min(0)).mean()
    alpha_loss = -(alpha * (logp - ACT)).mean()  # target entropy -|A|

    np.testing.assert_allclose(critic.target.numpy(), y, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(critic.q.numpy(), q, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(actor.log_prob.numpy(), logp, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(float(critic.loss.detach()), critic_loss, rtol=1e-5)
    np.testing.assert_allclose(float(actor.actor_loss.detach()), actor_loss, rtol=1e-5)
    np.testing.assert_allclose(float(actor.alpha_loss.detach()), alpha_loss, rtol=1e-5)


def test_critic_target_by_hand():
    """Constant networks make the soft Bellman target a formula one can write down."""
    sac = tiny_sac()
    with torch.no_grad():
        for p in [*sac.actor.parameters(), *sac.critic_target.parameters()]:
            p.zero_()
        sac.actor.layers[-1].bias.copy_(torch.tensor([0.2, -0.4, math.log(0.5), math.log(0.3)]))  # mean, log-std
        sac.critic_target.biases[-1].copy_(torch.tensor([[[1.5]], [[-2.0]]]))  # Q'_1 = 1.5, Q'_2 = -2
    eps = upcoming_noise(sac.target_generator, (B, ACT))
    batch = random_batch()
    target = sac.critic_terms(*tensors(batch), sac.log_alpha.detach().exp()).target.numpy()

    expected = []
    for i in range(B):
        log_pi = 0.0
        for j, (m, s) in enumerate([(0.2, 0.5), (-0.4, 0.3)]):
            u = m + s * eps[i, j]
            log_pi += -0.5 * eps[i, j] ** 2 - math.log(s) - 0.5 * math.log(2 * math.pi) - math.log(1 - math.tanh(u) ** 2)
        soft_v = min(1.5, -2.0) - 0.7 * log_pi
        expected.append(batch.reward[i] + 0.9 * (1 - batch.terminated[i]) * soft_v)
    np.testing.assert_allclose(target, expected, rtol=1e-5)
    # terminal transitions do not bootstrap: the target is the reward alone
    done = batch.terminated == 1
    np.testing.assert_allclose(target[done], batch.reward[done], rtol=1e-6)


def test_tanh_log_prob_matches_torch_distributions():
    torch.manual_seed(0)
    actor = Actor(OBS, ACT, hidden=(8,))
    obs = torch.randn(64, OBS)
    g = torch.Generator().manual_seed(1)
    action, log_prob = actor.sample(obs, generator=g)
    mean, log_std = actor(obs)
    dist = torch.distributions.TransformedDistribution(
        torch.distributions.Normal(mean, log_std.exp()), [torch.distributions.TanhTransform()])
    expected = dist.log_prob(action.clamp(-1 + 1e-6, 1 - 1e-6)).sum(-1)
    torch.testing.assert_close(log_prob, expected, rtol=1e-3, atol=1e-3)
    assert action.abs().max() < 1


def test_squashed_density_integrates_to_one():
    """The change-of-variables correction makes pi(a) a density on (-1, 1)."""
    actor = Actor(1, 1, hidden=(2,))
    with torch.no_grad():
        for p in actor.parameters():
            p.zero_()
        actor.layers[-1].bias.copy_(torch.tensor([0.8, math.log(0.9)]))  # mean 0.8, std 0.9
    u = torch.linspace(-12, 12, 200_001, dtype=torch.float64)
    a = torch.tanh(u)
    # log pi(a) from the actor's formula, evaluated at the u that produce a
    eps = (u - 0.8) / 0.9
    log_pi = -0.5 * eps**2 - math.log(0.9) - 0.5 * math.log(2 * math.pi) - 2 * (math.log(2) - u - torch.nn.functional.softplus(-2 * u))
    mass = torch.trapezoid(log_pi.exp(), a)
    assert abs(float(mass) - 1.0) < 1e-3
    # and it is the formula Actor.sample uses
    g = torch.Generator().manual_seed(0)
    action, lp = actor.sample(torch.zeros(1000, 1), generator=g)
    g = torch.Generator().manual_seed(0)
    e = torch.randn((1000, 1), generator=g).double()
    uu = 0.8 + 0.9 * e
    ref = (-0.5 * e**2 - math.log(0.9) - 0.5 * math.log(2 * math.pi) - torch.log1p(-torch.tanh(uu) ** 2)).sum(-1)
    torch.testing.assert_close(lp.double(), ref, rtol=1e-4, atol=1e-4)


def test_deterministic_action_is_tanh_of_mean():
    actor = Actor(OBS, ACT, hidden=(8,))
    obs = torch.randn(4, OBS)
    torch.testing.assert_close(actor.deterministic(obs), torch.tanh(actor(obs)[0]))


def test_polyak_target_update_exact_values():
    sac = tiny_sac(tau=0.25)
    with torch.no_grad():
        for p in sac.critic_target.parameters():
            p.fill_(2.0)
    sac.update(random_batch())
    for online, target in zip(sac.critic.parameters(), sac.critic_target.parameters()):
        torch.testing.assert_close(target, 2.0 + 0.25 * (online.detach() - 2.0), rtol=0, atol=1e-6)


def test_target_update_interval():
    sac = tiny_sac(target_update_interval=2)
    before = [p.clone() for p in sac.critic_target.parameters()]
    sac.update(random_batch(0))
    assert all(torch.equal(a, b) for a, b in zip(before, sac.critic_target.parameters()))
    sac.update(random_batch(1))
    assert not any(torch.equal(a, b) for a, b in zip(before, sac.critic_target.parameters()))


@pytest.mark.parametrize("parallel", [False, True])
def test_update_gradients_are_each_losss_own(parallel):
    """update() (serial or in two threads) must apply exactly each loss's gradient to its own
    parameters: the critic loss to the critics, the actor loss to the actor, J(alpha) to alpha."""
    sac = tiny_sac(parallel_branches=parallel)
    assert (sac._worker is not None) == parallel
    batch = random_batch()
    states = sac.target_generator.get_state(), sac.policy_generator.get_state()
    alpha = sac.log_alpha.detach().exp()
    critic = sac.critic_terms(*tensors(batch), alpha)
    actor = sac.actor_terms(torch.as_tensor(batch.obs), alpha)
    critic_params, actor_params = list(sac.critic.parameters()), list(sac.actor.parameters())
    # the actor loss must not push the critics, nor the critic loss the actor
    assert all(g is None for g in torch.autograd.grad(actor.actor_loss, critic_params, allow_unused=True,
                                                       retain_graph=True))
    assert all(g is None for g in torch.autograd.grad(critic.loss, actor_params, allow_unused=True,
                                                       retain_graph=True))
    expected_critic = torch.autograd.grad(critic.loss, critic_params)
    expected_actor = torch.autograd.grad(actor.actor_loss, actor_params)
    expected_alpha = torch.autograd.grad(actor.alpha_loss, [sac.log_alpha])

    sac.target_generator.set_state(states[0])
    sac.policy_generator.set_state(states[1])
    sac.update(batch)  # leaves the gradients it applied in .grad
    for g, p in zip(expected_critic, critic_params):
        torch.testing.assert_close(p.grad, g)
    for g, p in zip(expected_actor, actor_params):
        torch.testing.assert_close(p.grad, g)
    torch.testing.assert_close(sac.log_alpha.grad, expected_alpha[0])


def test_parallel_and_serial_updates_are_identical():
    serial, parallel = tiny_sac(parallel_branches=False), tiny_sac(parallel_branches=True)
    for i in range(5):
        assert serial.update(random_batch(i)) == parallel.update(random_batch(i))
    for k, v in serial.state_dict().items():
        assert torch.equal(v, parallel.state_dict()[k]), k


@pytest.mark.parametrize("target_entropy, direction", [(50.0, 1), (-50.0, -1)])
def test_temperature_moves_toward_target_entropy(target_entropy, direction):
    sac = tiny_sac(target_entropy=target_entropy)
    before = sac.alpha
    for i in range(5):
        sac.update(random_batch(i))
    assert (sac.alpha - before) * direction > 0


def test_fixed_alpha_is_not_trained():
    sac = tiny_sac(autotune_alpha=False, init_alpha=0.2)
    metrics = sac.update(random_batch())
    assert sac.alpha == pytest.approx(0.2) and metrics["alpha_loss"] == 0.0


def test_update_returns_finite_float_metrics_and_changes_all_networks():
    sac = tiny_sac()
    before = {k: v.clone() for k, v in sac.state_dict().items()}
    metrics = sac.update(random_batch())
    assert set(metrics) == set(METRICS)
    assert all(isinstance(v, float) and math.isfinite(v) for v in metrics.values())
    after = sac.state_dict()
    for prefix in ("actor.", "critic.", "critic_target.", "log_alpha"):
        assert any(not torch.equal(before[k], after[k]) for k in after if k.startswith(prefix)), prefix
    assert sac.num_updates == 1 and sac.update(random_batch(1), metrics=False) == {}


def test_update_accepts_dict_and_tensors():
    sac = tiny_sac()
    b = random_batch()
    sac.update({k: torch.as_tensor(getattr(b, k)) for k in ("obs", "action", "reward", "next_obs", "terminated")})
    assert sac.num_updates == 1


def test_act_shapes_and_range():
    sac = tiny_sac()
    single = sac.act(np.zeros(OBS, np.float32))
    batch = sac.act(np.zeros((6, OBS), np.float32), deterministic=True)
    assert single.shape == (ACT,) and batch.shape == (6, ACT)
    assert np.all(np.abs(batch) <= 1) and np.allclose(batch, batch[0])


def test_checkpoint_resumes_exactly(tmp_path):
    sac = tiny_sac()
    for i in range(3):
        sac.update(random_batch(i))
    path = sac.save_checkpoint(tmp_path / "learner.safetensors", extra={"env_steps": 1234})
    restored, extra = SAC.load_checkpoint(path)
    assert extra == {"env_steps": 1234} and restored.num_updates == 3
    assert restored.config == sac.config
    # the next update (same batch, same RNG stream, same Adam moments) is bit-identical
    m1, m2 = sac.update(random_batch(9)), restored.update(random_batch(9))
    assert m1 == m2
    for k, v in sac.state_dict().items():
        assert torch.equal(v, restored.state_dict()[k]), k


def test_fresh_learner_state_round_trips():
    sac, other = tiny_sac(), tiny_sac(seed=4)
    other.load_state_dict(sac.state_dict())
    assert sac.update(random_batch()) == other.update(random_batch())


def test_checkpoint_is_plain_safetensors_without_pickle(tmp_path, monkeypatch):
    sac = tiny_sac()
    sac.update(random_batch())
    path = sac.save_checkpoint(tmp_path / "c.safetensors")

    def forbidden(*a, **k):
        raise AssertionError("unpickling attempted")

    monkeypatch.setattr(pickle, "loads", forbidden)
    monkeypatch.setattr(pickle, "load", forbidden)
    monkeypatch.setattr(torch, "load", forbidden)
    SAC.load_checkpoint(path)
    with safetensors.safe_open(str(path), "pt") as f:
        assert "actor.layers.0.weight" in f.keys() and "adam.0.exp_avg" in f.keys()


def test_state_mismatch_is_reported():
    sac = tiny_sac()
    state = sac.state_dict()
    del state["critic.weights.1"]
    with pytest.raises(ValueError, match="missing.*critic.weights.1"):
        tiny_sac().load_state_dict(state)
    with pytest.raises(ValueError, match="shape"):
        SAC(OBS, ACT, SACConfig(hidden=(5, 4), device="cpu")).load_state_dict(sac.state_dict())


def test_corrupt_checkpoint_is_reported(tmp_path):
    path = tiny_sac().save_checkpoint(tmp_path / "c.safetensors")
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(ValueError, match="not a readable SAC checkpoint"):
        SAC.load_checkpoint(path)


def test_seeded_learners_are_reproducible():
    a, b = tiny_sac(), tiny_sac()
    assert a.update(random_batch()) == b.update(random_batch())
    c = tiny_sac(seed=5)
    assert not torch.equal(c.actor.layers[0].weight, a.actor.layers[0].weight)


def test_defaults_are_the_papers():
    cfg = SACConfig()
    assert (cfg.learning_starts, cfg.updates_per_step, cfg.total_steps, cfg.buffer_size) == (1000, 1.0, 1_000_000, 1_000_000)
    assert (cfg.batch_size, cfg.hidden, cfg.actor_lr, cfg.critic_lr, cfg.alpha_lr) == (256, (256, 256), 3e-4, 3e-4, 3e-4)
    assert (cfg.gamma, cfg.tau, cfg.target_update_interval, cfg.autotune_alpha) == (0.99, 0.005, 1, True)
    assert SAC(OBS, ACT, SACConfig(device="cpu", hidden=(4,))).target_entropy == -ACT


def test_device_selection():
    assert select_device("cpu") == torch.device("cpu")
    assert select_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_update_on_cuda_matches_shapes():
    sac = SAC(OBS, ACT, SACConfig(hidden=(8, 8), device="cuda"))
    metrics = sac.update(random_batch())
    assert all(math.isfinite(v) for v in metrics.values()) and sac.actor.layers[0].weight.is_cuda


def test_layer_norm_critic_of_its_own_width_matches_numpy_and_resumes(tmp_path):
    """critic_hidden / critic_layer_norm: each critic is Linear -> LayerNorm -> ReLU per hidden layer,
    its own width while the actor keeps `hidden`; the actor-loss path (frozen weights) gives the same
    Q; the checkpoint restores the layout and its next update is identical."""
    sac = tiny_sac(critic_hidden=(6, 5, 3), critic_layer_norm=True)
    assert [layer.out_features for layer in sac.actor.layers[:-1]] == [4, 4]
    with torch.no_grad():  # non-trivial affine parts, so a missing gain or shift would show
        for p in [*sac.critic.ln_gains, *sac.critic.ln_shifts]:
            p.uniform_(-1.5, 1.5)
    obs, act = random_batch(1).obs, random_batch(1).action
    x = np.concatenate([obs, act], 1).astype(np.float64)
    c = sac.critic
    first = torch.cat([c.obs_weight, c.act_weight], 1)
    for i in range(2):
        h = x
        for k, w in enumerate([first, *c.weights]):
            h = h @ w[i].detach().double().numpy() + c.biases[k][i, 0].detach().double().numpy()
            if k < 3:
                h = (h - h.mean(1, keepdims=True)) / np.sqrt(h.var(1, keepdims=True) + 1e-5)
                h = np.maximum(h * c.ln_gains[k][i, 0].detach().double().numpy()
                               + c.ln_shifts[k][i, 0].detach().double().numpy(), 0.0)
        q = c(torch.as_tensor(obs), torch.as_tensor(act))[i].detach().double().numpy()
        np.testing.assert_allclose(q, h[:, 0], rtol=1e-4, atol=1e-5)
    frozen = c.head(c.embed(torch.as_tensor(obs)), torch.as_tensor(act), frozen=True)
    assert torch.allclose(frozen, c(torch.as_tensor(obs), torch.as_tensor(act)))

    before = [p.detach().clone() for p in c.ln_gains]
    sac.update(random_batch(2))
    assert all(not torch.equal(a, b) for a, b in zip(before, c.ln_gains)), "LayerNorm gains are trained"
    restored, _ = SAC.load_checkpoint(sac.save_checkpoint(tmp_path / "ln.safetensors"))
    assert restored.config.critic_hidden == (6, 5, 3) and restored.config.critic_layer_norm
    assert sac.update(random_batch(3)) == restored.update(random_batch(3))


@pytest.mark.parametrize("sizes", [(), (4, 0)])
def test_empty_or_zero_width_networks_are_refused(sizes):
    with pytest.raises(ValueError, match="hidden"):
        SACConfig(critic_hidden=sizes)
