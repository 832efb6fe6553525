"""One policy for several objects (``env.objects``): which env steps which object, the object fields
of a transition batch, the learner's per-object figures, the evaluator's aggregate over objects, and
a policy file that records its object set and is tested on each by ``forcegrasp eval``."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from forcegrasp.config import ConfigError, load_config
from forcegrasp.evaluation import EvalResult
from forcegrasp.multi_object import AdaptiveObjectSampler, actor_index, aggregate, assign_objects, object_table, policy_objects, run_objects
from forcegrasp.policy_file import actor_param_shapes, load_policy_bytes, policy_to_bytes
from forcegrasp.protocol import ProtocolError, TransitionBatch, decode_transitions, encode_transitions
from forcegrasp.runtime import policy_metadata

REPO = Path(__file__).resolve().parent.parent
OBJECTS = ["mug", "camera", "power_drill", "spray_bottle"]


def config_of(*overrides, objects=OBJECTS, **extra):
    sets = [f"env.objects={json.dumps(objects)}", "env.max_steps=20", *overrides]
    return load_config(env={}, overrides=sets + [f"{k}={v}" for k, v in extra.items()])


# --------------------------------------------------------------------------------------------
# Configuration and assignment
# --------------------------------------------------------------------------------------------

def test_the_object_set_comes_from_flags_the_environment_and_compose():
    config = config_of()
    assert run_objects(config.env) == OBJECTS and config.env.object == "mug"  # object: the first entry
    assert run_objects(load_config(env={}, overrides=["env.object=camera"]).env) == ["camera"]
    from_env = load_config(env={"FORCEGRASP_ENV_OBJECTS": "camera,spray_bottle"})
    assert from_env.env.objects == ["camera", "spray_bottle"] and from_env.env.object == "camera"
    for bad in ('["mug", "mug"]', '["mug", "teapot"]'):
        with pytest.raises(ConfigError, match="env.objects"):
            load_config(env={}, overrides=[f"env.objects={bad}"])
    # compose passes FORCEGRASP_ENV_OBJECTS to every service; its empty default means env.object alone
    common = yaml.safe_load((REPO / "compose.yaml").read_text())["x-common"]["environment"]
    assert common["FORCEGRASP_ENV_OBJECTS"] == "${FORCEGRASP_ENV_OBJECTS:-}"
    env = {"FORCEGRASP_ENV_OBJECT": "mug", "FORCEGRASP_ENV_OBJECTS": ""}
    assert run_objects(load_config(env=env).env) == ["mug"]
    assert run_objects(load_config(env={**env, "FORCEGRASP_ENV_OBJECTS": "mug,camera"}).env) == ["mug", "camera"]


def test_envs_of_the_actors_go_round_the_object_set():
    assert [actor_index(i) for i in ("actor-0", "actor-7", "actor-3.host7")] == [0, 7, 3]
    assert actor_index("actor-abc") == actor_index("actor-abc")  # a stable hash for other ids
    # enough envs: every actor steps every object, twice here
    for i in range(3):
        got = assign_objects(OBJECTS, 8, i)
        assert sorted(got) == sorted(OBJECTS * 2)
    # fewer envs than objects: the actors' envs follow on from each other, together covering the set
    assert assign_objects(OBJECTS, 2, 0) == ["mug", "camera"]
    assert assign_objects(OBJECTS, 2, 1) == ["power_drill", "spray_bottle"]
    three = [o for i in range(4) for o in assign_objects(OBJECTS, 3, i)]
    assert {o: three.count(o) for o in OBJECTS} == dict.fromkeys(OBJECTS, 3)
    assert assign_objects(["mug"], 4, 5) == ["mug"] * 4


def test_an_actor_steps_all_its_objects_and_its_batch_says_which(caplog):
    from forcegrasp.acting import Actor

    config = config_of("actor.envs_per_actor=4", "actor.demo_episodes=0", "actor.random_steps=100000",
                       "actor.publish_batch=100000", "learner.recipe=paper")
    actor = Actor(config, "actor-1", seed=0)
    try:
        assert actor.env_objects == ["mug", "camera", "power_drill", "spray_bottle"]
        assert [env.object_spec.name for env in actor.envs] == actor.env_objects
        for _ in range(25):  # past max_steps = 20: every env ends an episode
            actor.step()
        batch = actor._package()
        assert batch.objects == OBJECTS
        n_env = batch.n // 4
        assert np.bincount(batch.object_index, minlength=4).tolist() == [n_env] * 4
        # the rows of one env are that env's: goal pose and palm (the last 9 numbers) name its object
        goal = batch.obs[:, -9:]
        for k in range(4):
            rows = goal[batch.object_index == k]
            assert np.allclose(rows, rows[0]) and not np.allclose(rows[0], goal[batch.object_index != k][0])
        assert sorted(batch.episode_objects.tolist()) == [0, 1, 2, 3]
        assert actor.stats()["objects"] == {o: {"episodes": 1, "successes": 0} for o in OBJECTS}
        back = decode_transitions(encode_transitions(batch), obs_dim=actor.obs_dim, act_dim=7)
        assert back.objects == OBJECTS and np.array_equal(back.object_index, batch.object_index)
    finally:
        actor.close()
    # an actor of fewer envs than objects says which it leaves to the others
    spare = Actor(config_of("actor.envs_per_actor=1", "actor.demo_episodes=0"), "actor-2", seed=0)
    assert spare.env_objects == ["power_drill"] and "step power_drill of the 4 objects" in caplog.text
    spare.close()


def test_demonstrations_follow_each_envs_object():
    from forcegrasp.acting import Actor
    from forcegrasp.recipes import demo_episodes

    actor = Actor(config_of("actor.envs_per_actor=2", objects=["camera", "mug"]), "actor-0", seed=0)
    assert actor._demos_left == [demo_episodes("camera", -1), demo_episodes("mug", -1)]
    assert all(d.env is env for d, env in zip(actor._demo, actor.envs))
    actor.close()


def test_adaptive_sampling_sends_episodes_to_the_objects_that_fail():
    sampler = AdaptiveObjectSampler(["mug", "camera", "drill"], np.random.default_rng(0), window=4, mix=0.5)
    assert np.allclose(sampler.probabilities(), 1 / 3)  # nothing seen: every object fails alike
    for ok in (False, False, True, True, True, True):  # the window keeps the last 4: camera solved
        sampler.record("camera", ok)
    for ok in (True, False, False, False):
        sampler.record("mug", ok)  # 1 of 4: fails 3/4
    sampler.record("drill", True), sampler.record("drill", False)  # fails 1/2
    # p = 0.5 / 3 + 0.5 * fail / sum(fail), fail = (0.75, 0, 0.5)
    assert np.allclose(sampler.probabilities(), [1 / 6 + 0.5 * 0.6, 1 / 6, 1 / 6 + 0.5 * 0.4])
    draws = [sampler.draw() for _ in range(3000)]
    assert abs(draws.count("mug") / 3000 - 0.4667) < 0.03 and abs(draws.count("camera") / 3000 - 1 / 6) < 0.03
    for name in ("mug", "drill"):
        for _ in range(4):
            sampler.record(name, True)
    assert np.allclose(sampler.probabilities(), 1 / 3)  # all solved: uniform again
    with pytest.raises(ConfigError, match="object_sampling"):
        config_of("env.object_sampling=greedy")


def test_adaptive_actor_moves_its_envs_between_objects_and_labels_every_row():
    from forcegrasp.acting import Actor

    config = config_of("env.object_sampling=adaptive", "actor.envs_per_actor=2", "actor.demo_episodes=0",
                       "actor.random_steps=100000", "actor.publish_batch=100000", "learner.recipe=paper",
                       "env.max_steps=3")
    actor = Actor(config, "actor-0", seed=0)
    try:
        assert actor.env_objects == ["mug", "camera"]  # the assignment picks the first episodes' objects
        stepped = set()
        for _ in range(3 * 16):  # 16 episodes of 3 steps per slot
            actor.step()
            stepped.update(actor.env_objects)
            assert [env.object_spec.name for env in actor.envs] == actor.env_objects
        assert stepped == set(OBJECTS)  # random actions fail everywhere: every object gets drawn
        assert all(len(pool) > 1 for pool in actor._pool)
        batch = actor._package()
        goal = batch.obs[:, -9:]  # the goal pose and palm name the object a row came from
        for k in np.unique(batch.object_index):
            rows = goal[batch.object_index == k]
            assert np.allclose(rows, rows[0]) and not np.allclose(rows[0], goal[batch.object_index != k][0])
        assert sum(v["episodes"] for v in actor.stats()["objects"].values()) == 32
    finally:
        actor.close()
    # one object (an actor on a spare machine): nothing to draw
    single = Actor(config_of("env.object_sampling=adaptive", "actor.envs_per_actor=1", "actor.demo_episodes=0",
                             objects=["camera"]), "actor-0", seed=0)
    assert single.sampler is None
    single.close()


# --------------------------------------------------------------------------------------------
# The wire
# --------------------------------------------------------------------------------------------

def batch_of(n=6, episodes=2, **fields) -> TransitionBatch:
    rng = np.random.default_rng(0)
    b = TransitionBatch("actor-0", 0, 0, rng.standard_normal((n, 77)), rng.uniform(-1, 1, (n, 7)),
                        rng.standard_normal(n), rng.standard_normal((n, 77)), np.zeros(n, bool), np.zeros(n, bool),
                        objects=["mug", "camera"], object_index=np.arange(n) % 2)
    if episodes:
        b.episode_returns, b.episode_lengths = np.zeros(episodes), np.ones(episodes, np.int32)
        b.episode_successes, b.episode_objects = np.zeros(episodes, bool), np.arange(episodes) % 2
    return dataclasses.replace(b, **fields)


def test_object_fields_round_trip_and_are_optional():
    got = decode_transitions(encode_transitions(batch_of()), obs_dim=77, act_dim=7)
    assert got.objects == ["mug", "camera"] and got.object_index.dtype == np.uint8
    assert got.object_index.tolist() == [0, 1] * 3 and got.episode_objects.tolist() == [0, 1]
    plain = decode_transitions(encode_transitions(batch_of(episodes=0, objects=None, object_index=None)))
    assert plain.objects is None and plain.object_index is None and plain.episode_objects is None


@pytest.mark.parametrize("fields, reason", [
    ({"object_index": np.array([0, 1, 2, 0, 1, 0])}, "bad_field"),  # points past the names
    ({"episode_objects": np.array([0, 2])}, "bad_field"),
    ({"object_index": np.array([0, -1, 0, 0, 0, 0])}, "bad_field"),  # a byte cannot hold it
    ({"object_index": np.array([0, 300, 0, 0, 0, 0])}, "bad_field"),
    ({"object_index": np.array([0.0, 1, 0, 1, 0, 1])}, "bad_field"),  # not integers
    ({"object_index": np.array([0, 1, 0])}, "shape"),
    ({"objects": ["mug", "mug"]}, "bad_field"),  # names must be distinct
    ({"objects": ["mug/x", "camera"]}, "bad_field"),
    ({"objects": []}, "bad_field"),
    ({"objects": None}, "missing_field"),  # indices without names
    ({"object_index": None}, "missing_field"),
    ({"episode_objects": None}, "missing_field"),  # episodes of unknown objects
])
def test_bad_object_fields_are_refused_at_both_ends(fields, reason):
    with pytest.raises(ProtocolError) as info:
        encode_transitions(batch_of(**fields))
    assert info.value.reason == reason
    # a sender that skips the checks: the receiver refuses the same message
    import msgpack

    good = msgpack.unpackb(encode_transitions(batch_of()), raw=False)
    if "objects" in fields:
        good.pop("objects") if fields["objects"] is None else good.update(objects=fields["objects"])
    for key, wire in (("object_index", "object_index"), ("episode_objects", "ep_object")):
        if key in fields:
            value = fields[key]
            if value is None:
                good.pop(wire)
            else:
                arr = np.asarray(value)
                arr = arr.astype(np.uint8) if arr.dtype.kind == "i" and arr.min() >= 0 and arr.max() < 256 else arr
                good[wire] = {"dtype": arr.dtype.str, "shape": list(arr.shape), "data": arr.tobytes()}
    with pytest.raises(ProtocolError):
        decode_transitions(msgpack.packb(good, use_bin_type=True), obs_dim=77, act_dim=7)


def test_the_learner_counts_success_per_object_and_refuses_foreign_objects(tmp_path):
    from forcegrasp_learner.learner import LearnerService

    config = config_of(f"run.output_dir={tmp_path}", "learner.recipe=paper", "learner.sac.hidden=[8, 8]",
                       objects=["mug", "camera"])
    learner = LearnerService(config)
    key = learner.keys.transitions("actor-0")
    batch = batch_of(episodes=3, episode_successes=np.array([True, False, True]),
                     episode_objects=np.array([0, 1, 0]))
    assert learner.ingest(key, encode_transitions(batch)) == 6
    objects = learner.stats(1.0, 0, 0)["objects"]
    assert objects == {"mug": {"episodes": 2, "success_rate": 1.0}, "camera": {"episodes": 1, "success_rate": 0.0}}
    zeros = {"object_index": np.zeros(6, np.uint8), "episode_objects": np.zeros(2, np.uint8)}
    spare = batch_of(seq=1, objects=["power_drill"], **zeros)
    assert learner.ingest(key, encode_transitions(spare)) == 0
    assert learner.rejects.counts() == {"foreign_object": 1} and learner.ingested == 6
    part = batch_of(seq=2, objects=["camera"], **zeros)
    assert learner.ingest(key, encode_transitions(part)) == 6  # a spare actor for one of the run's objects
    meta = learner.metadata()
    assert meta.object_name == "" and meta.extra["objects"] == ["mug", "camera"]


# --------------------------------------------------------------------------------------------
# The evaluator
# --------------------------------------------------------------------------------------------

def test_aggregates_on_a_hand_made_example():
    assert aggregate([3.0, 1.0, 2.0]) == 1.0 and aggregate([3.0, 1.0, 2.0], "mean") == 2.0
    with pytest.raises(ValueError):
        aggregate([1.0], "median")
    lines = object_table({"mug": {"score": 5.0, "success_rate": 1.0, "episodes": 2},
                          "camera": {"score": 1.0, "success_rate": 0.5, "episodes": 2}}, "min")
    assert lines[-1] == "| min over objects | 50% | 1.0 | 4 |"


def ev_config(tmp_path, *extra, objects=("camera", "mug")):
    """A run scored under its own env unless ``extra`` names test conditions."""
    return config_of(f"run.output_dir={tmp_path / 'runs'}", "run.name=multi", "evaluator.eval_every=1000",
                     "evaluator.eval_episodes=2", "evaluator.final_rank_episodes=3", "evaluator.http_port=0",
                     "evaluator.conditions=[]", *extra, objects=list(objects))


def checkpoint(config, step, hidden=(8,)):
    meta = policy_metadata(config, hidden, training_steps=step, policy_version=1)
    data = policy_to_bytes({k: np.zeros(s, np.float32) for k, s in actor_param_shapes(meta).items()}, meta)
    path = Path(config.run.output_dir) / config.run.name / "checkpoints" / f"policy-{step:09d}.safetensors"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


#: Hand-made scores per (object, condition): the camera is this policy's worst object.
MADE = {("camera", "5x"): (2.0, 0.5), ("camera", "1x_3cm"): (0.0, 0.0),
        ("mug", "5x"): (10.0, 1.0), ("mug", "1x_3cm"): (6.0, 1.0)}


@pytest.mark.parametrize("how, score, success", [("min", 1.0, 0.25), ("mean", 4.5, 0.625)])
def test_the_evaluator_ranks_on_the_aggregate_over_objects(tmp_path, capsys, how, score, success):
    """Per object the conditions' mean (camera 1.0, mug 8.0), across objects the aggregate; the member,
    its file, the history, the /best page and `forcegrasp best` keep every object's figures."""
    from forcegrasp import topk
    from forcegrasp_evaluator import client
    from forcegrasp_evaluator.endpoint import EvaluatorHTTPServer
    from forcegrasp_evaluator.evaluator import EvaluatorService

    config = ev_config(tmp_path, 'evaluator.conditions=["5x", "1x_3cm"]', f"evaluator.object_aggregate={how}")
    seen = []

    def score_fn(policy, weights, meta, places, kind, step, condition=None, object=None):  # noqa: A002
        seen.append((kind, object, condition, len(places)))
        value, rate = MADE[object, condition]
        return EvalResult(score=value + (0.5 if kind == "rank" else 0.0), success_rate=rate, episodes=len(places))

    with EvaluatorService(config, score_fn=score_fn, log_episodes=False) as service:
        assert service._ensure_env("5x", "mug").object_spec.name == "mug"
        service.load()
        checkpoint(config, 1000)
        service.scan()
        member = service.process(*service.next_checkpoint())
        best_page = json.loads(service.snapshot.best_json)
        http = EvaluatorHTTPServer("127.0.0.1", 0, lambda: service.snapshot).start()
        try:
            capsys.readouterr()
            out = tmp_path / "best.safetensors"
            assert client.main(["--out", str(out), "--url", f"http://127.0.0.1:{http.port}"]) == 0
        finally:
            http.stop()
    printed = capsys.readouterr()
    assert json.loads(printed.out)["objects"]["mug"]["success_rate"] == 1.0
    assert "| camera | 25% | 1.5 | 6 |" in printed.err and f"| {how} over objects |" in printed.err
    assert sorted(seen) == sorted([(k, o, c, 2 if k == "eval" else 3) for k in ("eval", "rank") for o, c in MADE])
    assert member.score == pytest.approx(score) and member.success_rate == pytest.approx(success)
    assert member.rank_score == pytest.approx(score + 0.5) and member.episodes == 8 and member.rank_episodes == 12
    assert {o: v["score"] for o, v in member.objects.items()} == {"camera": 1.5, "mug": 8.5}
    assert member.objects["camera"]["conditions"]["1x_3cm"]["success_rate"] == 0.0
    assert member.object == ""  # a policy of several objects names no one of them
    index = topk.check_folder(Path(config.run.output_dir) / "multi" / "evaluator" / "top", k=5)
    assert index["protocol"]["objects"] == ["camera", "mug"] and index["protocol"]["object_aggregate"] == how
    assert index["history"][0]["objects"]["mug"]["score"] == 8.0
    assert best_page["objects"]["camera"]["success_rate"] == 0.25 and best_page["object"] == ""
    _, meta = load_policy_bytes(service.top.read_policy(member))
    evaluation = meta.extra["evaluation"]
    assert evaluation["rank_objects"]["mug"]["score"] == 8.5 and evaluation["object_aggregate"] == how
    assert policy_objects(meta) == ["camera", "mug"]


def test_episode_logs_are_per_object_and_other_object_sets_are_rejected(tmp_path):
    """Real rollouts (two episodes of 20 steps): the logs are eval-<object>-<i>; a checkpoint of a
    single-object run is not this run's."""
    from forcegrasp_evaluator.evaluator import EvaluatorService

    config = ev_config(tmp_path, "evaluator.final_rank_episodes=1", "evaluator.top_k=1")
    with EvaluatorService(config) as service:
        service.load()
        checkpoint(config, 1000)
        service.scan()
        member = service.process(*service.next_checkpoint())
        assert member is not None and set(member.objects) == {"camera", "mug"}
        logs = sorted(p.name for p in (service.episodes_dir / "000001000").iterdir())
        assert logs == ["eval-camera-000.mcap", "eval-camera-001.mcap", "eval-mug-000.mcap", "eval-mug-001.mcap",
                        "rank-camera-000.mcap", "rank-mug-000.mcap"]
        checkpoint(load_config(env={}, overrides=[f"run.output_dir={tmp_path / 'runs'}", "run.name=multi",
                                                  "env.object=camera"]), 3000)
        service.scan()
        assert service.process(*service.next_checkpoint()) is None and service.counters.bad_checkpoints == 1


# --------------------------------------------------------------------------------------------
# Policy files and forcegrasp eval
# --------------------------------------------------------------------------------------------

def test_a_policy_file_records_its_objects_and_eval_runs_it_on_each(tmp_path, capsys):
    from forcegrasp.cli.policy_eval import main

    config = config_of(objects=["camera", "spray_bottle"])
    meta = policy_metadata(config, (8,))
    assert meta.object_name == "" and meta.extra["objects"] == ["camera", "spray_bottle"]
    path = tmp_path / "p.safetensors"
    path.write_bytes(policy_to_bytes({k: np.zeros(s, np.float32) for k, s in actor_param_shapes(meta).items()}, meta))
    assert policy_objects(load_policy_bytes(path.read_bytes())[1]) == ["camera", "spray_bottle"]
    out = tmp_path / "rows.json"
    assert main([str(path), "--episodes", "1", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [r["object"] for r in rows] == ["camera", "spray_bottle"] and all(r["episodes"] == 1 for r in rows)
    text = capsys.readouterr().out
    assert "| object | settings | success |" in text and "| spray_bottle | as given |" in text
    assert "| worst object | as given |" in text
    assert main([str(path), "--episodes", "1", "--object", "spray_bottle", "--json", str(out)]) == 0
    assert [r["object"] for r in json.loads(out.read_text())["rows"]] == ["spray_bottle"]
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main([str(path), "--episodes", "1", "--object", "mug"])
    assert "trained on camera, spray_bottle" in capsys.readouterr().err
    # a single-object run's policy is as before: its object, no set
    single = policy_metadata(load_config(env={}, overrides=["env.object=camera"]), (8,))
    assert single.object_name == "camera" and "objects" not in single.extra and policy_objects(single) == ["camera"]


def test_experiment_marks_of_a_multi_object_run_are_tested_on_each_object(tmp_path):
    """`forcegrasp experiment` tests a generalist's marks on every object (under every condition) and
    aggregates them as the run's evaluator ranks them (the minimum by default)."""
    from forcegrasp.cli.experiment import summary_lines, test_marks

    config = config_of(objects=["camera", "mug"])
    meta = policy_metadata(config, (8,))
    (tmp_path / "marks").mkdir()
    weights = {k: np.full(s, 0.05, np.float32) for k, s in actor_param_shapes(meta).items()}
    (tmp_path / "marks" / "best-001.0.safetensors").write_bytes(policy_to_bytes(weights, meta))
    record = {"label": "generalist", "seed": 0, "episodes": 2, "test_seed": 0, "test_env": {"max_steps": 20},
              "conditions": ["5x", "noise_0.5"], "objects": ["camera", "mug"], "object_aggregate": "min",
              "marks": [{"minute": 1.0, "files": {"best": "best-001.0.safetensors"}, "steps": {}, "test": {}}]}
    test_marks(tmp_path, record, workers=1, log=lambda m: None)
    score = record["marks"][0]["test"]["best"]
    each = score["objects"]
    assert list(each) == ["camera", "mug"] and score["episodes"] == 8
    assert all(set(e["conditions"]) == {"5x", "noise_0.5"} and e["episodes"] == 4 for e in each.values())
    assert score["mean_return"] == min(e["mean_return"] for e in each.values())
    assert score["success_rate"] == min(e["success_rate"] for e in each.values())
    assert each["camera"]["mean_return"] != each["mug"]["mean_return"]  # really two objects' episodes
    assert "the min over objects camera, mug" in summary_lines(record)[0] and "camera " in summary_lines(record)[1]
    # --plot draws one curve per object, from that object's own figures
    from forcegrasp.cli.experiment_plot import curves, plot_records

    drawn = curves([record])
    assert [c["group"] for c in drawn] == ["generalist: camera", "generalist: mug"]
    assert [c["points"][0][2] for c in drawn] == [each["camera"]["success_rate"], each["mug"]["success_rate"]]
    assert plot_records([record], tmp_path / "g.png").stat().st_size > 10_000


def test_eval_tests_a_generalist_zero_shot_on_an_object_it_never_saw(tmp_path, capsys):
    """Leave-one-out: ``forcegrasp eval --unseen NAME`` runs the policy on an object outside its set;
    the row says so and stays out of the worst object's figures."""
    from forcegrasp.cli.policy_eval import main

    meta = policy_metadata(config_of(objects=["camera", "spray_bottle"]), (8,))
    path = tmp_path / "p.safetensors"
    path.write_bytes(policy_to_bytes({k: np.zeros(s, np.float32) for k, s in actor_param_shapes(meta).items()}, meta))
    out = tmp_path / "rows.json"
    assert main([str(path), "--episodes", "1", "--unseen", "mug", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["object"], r["zero_shot"]) for r in rows] == [("camera", False), ("spray_bottle", False), ("mug", True)]
    assert rows[2]["env"]["mass_scale"] == 5.0 and rows[2]["episodes"] == 1
    text = capsys.readouterr().out
    assert "| mug (unseen) | as given |" in text
    worst = min(rows[:2], key=lambda r: r["mean_return"])["mean_return"]
    assert f"| worst object | as given | 0% | {worst:.1f} |" in text
    for bad, message in (("camera", "trained on it"), ("teapot", "unknown object")):
        with pytest.raises(SystemExit):
            main([str(path), "--episodes", "1", "--unseen", bad])
        assert message in capsys.readouterr().err
