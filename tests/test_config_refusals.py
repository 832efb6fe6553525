"""Every command refuses a bad configuration before it starts anything: a misspelt key or an
ill-typed value in any section (``[learner.sac]`` included) is exit code 2 with a message naming
the key, the value and what is allowed, and nothing is written."""

from __future__ import annotations

import pytest

from forcegrasp.cli import main

COMMANDS = ["up", "train", "experiment", "learner", "actor", "evaluator"]
#: (override, what the message must name): one misspelt key and one ill-typed value per section.
BAD = [
    ("run.nmae=x", "run.nmae"), ("run.seed=abc", "run.seed"),
    ("env.objct=mug", "env.objct"), ("env.jitter=wide", "env.jitter"),
    ("actor.envs=4", "actor.envs"), ("actor.envs_per_actor=1.5", "actor.envs_per_actor"),
    ("network.lease=5", "network.lease"), ("network.lease_ms=soon", "network.lease_ms"),
    ("learner.broadcast=5", "learner.broadcast"), ("learner.checkpoint_every=-3", "learner.checkpoint_every"),
    ("learner.sac.batchsize=512", "learner.sac.batchsize"), ("learner.sac.batch_size=abc", "learner.sac.batch_size"),
    ("learner.sac.hidden=[64, \"wide\"]", "learner.sac.hidden"), ("learner.sac.gamma=1.5", "learner.sac.gamma"),
    ("evaluator.topk=3", "evaluator.topk"), ("evaluator.top_k=many", "evaluator.top_k"),
    ("evaluator.conditions=[\"moon\"]", "moon"), ("env.mass_scale_range=[5, 0.5]", "env.mass_scale_range"),
]


@pytest.mark.parametrize("command", COMMANDS)
def test_bad_configuration_is_refused_before_anything_starts(command, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    for override, named in BAD:
        rc = main([command, "--set", f"run.output_dir={tmp_path / 'runs'}", "--set", override])
        err = capsys.readouterr().err
        assert rc == 2, (command, override, err)
        assert named in err and "error:" in err, (command, override, err)
        assert not any(tmp_path.iterdir()), f"{command} --set {override} wrote {list(tmp_path.iterdir())}"


def test_messages_say_what_is_allowed(capsys):
    main(["learner", "--set", "learner.sac.batchsize=512"])
    err = capsys.readouterr().err
    assert "unknown SAC setting" in err and "known: " in err and "batch_size" in err.split("known: ")[1]
    main(["learner", "--set", "learner.sac.batch_size=abc"])
    assert "'abc' is not a whole number" in capsys.readouterr().err
    main(["up", "--set", "evaluator.conditions=[\"moon\"]"])
    assert "known: 5x" in capsys.readouterr().err
