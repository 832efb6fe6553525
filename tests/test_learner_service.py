"""Learner service settings that act without the network: replay snapshots and seeds."""

import numpy as np

from forcegrasp.config import load_config
from forcegrasp.cli.up import service_commands
from forcegrasp.protocol import Keys, TransitionBatch, encode_transitions
from forcegrasp_learner.learner import LearnerService


def _config(tmp_path, *extra):
    return load_config(overrides=[f"run.output_dir={tmp_path}", "run.name=r", "learner.sac.hidden=[8, 8]",
                                  "learner.sac.buffer_size=1000", "learner.recipe=paper", *extra])


def _feed(service, n=32, seq=0):
    rng = np.random.default_rng(seq)
    batch = TransitionBatch("a", seq, 0, rng.normal(size=(n, 77)), rng.uniform(-1, 1, (n, 7)), rng.normal(size=n),
                            rng.normal(size=(n, 77)), np.zeros(n, bool), np.zeros(n, bool))
    assert service.ingest(Keys("r").transitions("a"), encode_transitions(batch)) == n


def test_snapshot_replay_false_checkpoints_without_the_replay_and_resumes_empty(tmp_path):
    service = LearnerService(_config(tmp_path, "learner.snapshot_replay=false"))
    _feed(service)
    service.checkpoint()
    assert not (tmp_path / "r" / "replay.npz").exists() and (tmp_path / "r" / "checkpoint.safetensors").exists()
    again = LearnerService(_config(tmp_path, "learner.snapshot_replay=false"))
    assert again.ingested == 32 and len(again.buffer) == 0
    with_replay = LearnerService(_config(tmp_path / "b"))
    _feed(with_replay)
    with_replay.checkpoint()
    assert len(LearnerService(_config(tmp_path / "b")).buffer) == 32


def test_actor_seeds_follow_run_seed(tmp_path):
    seeds = {s: [c[c.index("--seed") + 1] for name, c in service_commands(tmp_path / "c.toml", 2, seed=s).items()
                 if name.startswith("actor")] for s in (0, 7)}
    assert seeds == {0: ["1000", "2000"], 7: ["1007", "2007"]}


def test_recipes_are_presets_under_the_overrides(tmp_path, monkeypatch):
    import pytest

    import forcegrasp.recipes
    from forcegrasp.config import ConfigError
    from forcegrasp.recipes import demo_episodes, sac_config
    from forcegrasp.sac import SACConfig

    paper = sac_config(_config(tmp_path, "learner.recipe=paper"))
    assert paper.updates_per_step == SACConfig().updates_per_step and not paper.privileged_critic
    assert not paper.critic_layer_norm
    fast = sac_config(_config(tmp_path, "learner.recipe=fast", "learner.sac.batch_size=128"))
    assert fast.updates_per_step == 0.25 and fast.privileged_critic and fast.batch_size == 128
    assert fast.critic_layer_norm
    mine = sac_config(_config(tmp_path, "learner.recipe=fast", "learner.sac.privileged_critic=false"))
    assert not mine.privileged_critic  # an override beats the preset
    # per-object settings (OBJECT_RECIPES) go on the preset, under the overrides, for their recipe only
    monkeypatch.setitem(forcegrasp.recipes.OBJECT_RECIPES, "fast", {"camera": {"critic_layer_norm": False}})
    assert not sac_config(_config(tmp_path, "learner.recipe=fast", "env.object=camera")).critic_layer_norm
    assert sac_config(_config(tmp_path, "learner.recipe=fast", "env.object=mug")).critic_layer_norm
    assert sac_config(_config(tmp_path, "learner.recipe=fast", "env.object=camera",
                                  "learner.sac.critic_layer_norm=true")).critic_layer_norm
    # demonstrations: -1 is the object's number (4 on every object today), an explicit one is taken as is
    assert [demo_episodes(o, -1) for o in ("mug", "camera", "power_drill", "spray_bottle")] == [4, 4, 4, 4]
    assert demo_episodes("camera", 0) == 0 and demo_episodes("mug", 2) == 2
    with pytest.raises(ConfigError):
        _config(tmp_path, "learner.recipe=magic")


def test_update_debt_past_its_cap_is_forgone_and_counted(tmp_path, monkeypatch):
    import forcegrasp.learning

    monkeypatch.setattr(forcegrasp.learning, "MAX_UPDATE_DEBT", 40)
    service = LearnerService(_config(tmp_path, "learner.sac.learning_starts=0", "learner.sac.batch_size=8"))
    _feed(service)
    assert service.updates_due == 32 and service.updates_forgone == 0
    _feed(service, seq=1)  # 64 owed, 40 kept
    assert service.updates_due == 40 and service.updates_forgone == 24
    service.train(100)
    stats = service.stats(1.0, 0, 0)
    assert (stats["updates"], stats["update_debt"], stats["updates_forgone"]) == (40, 0.0, 24)
    assert stats["updates"] + stats["update_debt"] + stats["updates_forgone"] == stats["ingested"]
