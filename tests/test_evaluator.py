"""Evaluator: placements, top-k selection and its crash safety, MCAP logs, replay, the endpoints.

In-process tests use the real service class (an injected scoring function where the test needs
scores it controls) and real files; ``test_evaluator_service.py`` runs the service as a process.

Policies with *known* scores: a policy whose weights are all zero acts with the constant action
``tanh(last bias)``. Backing the hand base away from the camera (the third translation, negative)
at a constant speed ``s`` (fraction of the maximal 4 mm step) gives a return that falls strictly
with ``s`` on every placement (the palm error grows faster), so the best five of a set of speeds
are the five slowest.
"""

from __future__ import annotations

import hashlib
import http.client
import importlib.util
import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
import pytest

from forcegrasp.config import load_config
from forcegrasp.policy_file import atomic_write, actor_param_shapes, load_policy_bytes, policy_to_bytes
from forcegrasp.protocol import ProtocolError
from forcegrasp.runtime import policy_metadata
from forcegrasp import topk
from forcegrasp.protocol.best import BestPolicy, decode_best, encode_best
from forcegrasp_evaluator.endpoint import BestFetchError, EvaluatorHTTPServer, Snapshot, fetch_best_http
from forcegrasp.evaluation import EvalResult, evaluate, placements
from forcegrasp_evaluator.evaluator import EvaluatorService

HIDDEN = (32, 32)


def tiny_config(tmp_path, run="ev", **extra):
    """A short-episode run scored under its own env alone (the mix of test conditions has its own tests)."""
    overrides = [f"run.name={run}", f"run.output_dir={tmp_path / 'runs'}", "env.object=camera",
                 "env.max_steps=20", "evaluator.eval_every=1000", "evaluator.eval_episodes=2",
                 "evaluator.final_rank_episodes=3", "evaluator.top_k=5", "evaluator.http_port=0",
                 "evaluator.conditions=[]"]
    overrides += [f"{k}={v}" for k, v in extra.items()]
    return load_config(env={}, overrides=overrides)


def policy_bytes(config, step, speed=0.0, hidden=HIDDEN, **extra) -> bytes:
    """A policy acting with the constant action (0, 0, -speed, 0, ...); ``extra`` goes to its metadata."""
    meta = policy_metadata(config, hidden, training_steps=step, policy_version=step // 1000, **extra)
    weights = {k: np.zeros(s, np.float32) for k, s in actor_param_shapes(meta).items()}
    weights[f"layers.{len(hidden)}.bias"][2] = np.arctanh(-speed)
    return policy_to_bytes(weights, meta)


def write_checkpoint(config, step, data: bytes) -> Path:
    path = Path(config.run.output_dir) / config.run.name / "checkpoints" / f"policy-{step:09d}.safetensors"
    with atomic_write(path) as f:
        f.write(data)
    return path


def fake_score(policy, weights, meta, places, kind, step, condition=None) -> EvalResult:
    """Scores read from the policy's metadata: the test decides them."""
    return EvalResult(score=float(meta.extra["fake"][kind]), success_rate=0.25, episodes=len(places))


def top_dir(config) -> Path:
    return Path(config.run.output_dir) / config.run.name / "evaluator" / "top"


def expected_top(scores: dict[int, float], k=5) -> list[int]:
    return [s for s, _ in sorted(scores.items(), key=lambda kv: (-kv[1], kv[0]))[:k]]


# --------------------------------------------------------------------------------------------
# Placements
# --------------------------------------------------------------------------------------------

def test_placements_are_fixed_per_seed_and_stream():
    a, b = placements(7, 10, 0.02, "eval"), placements(7, 10, 0.02, "eval")
    assert a == b
    assert placements(7, 4, 0.02, "eval") == a[:4]  # more episodes extend, never reshuffle
    assert placements(8, 10, 0.02, "eval") != a
    assert placements(7, 10, 0.02, "rank")[:3] != a[:3]
    offsets = np.array([p.offset for p in placements(7, 200, 0.02, "rank")])
    assert np.abs(offsets).max() <= 0.02 and offsets.std() > 0.008  # spread over the jitter square
    assert len({p.seed for p in a}) == 10


# --------------------------------------------------------------------------------------------
# Top k with injected scores
# --------------------------------------------------------------------------------------------

def test_stream_of_known_scores_leaves_exactly_the_right_five(tmp_path):
    config = tiny_config(tmp_path)
    rng = np.random.default_rng(3)
    eval_scores = rng.permutation([3.0, 9.0, 1.0, 9.0, 7.0, 2.0, 8.0, 5.0, 6.0, 4.0, 9.5, 0.5, 7.0, 10.0])
    scores, rank_scores = {}, {}
    with EvaluatorService(config, score_fn=fake_score, log_episodes=False) as service:
        service.load()
        for i, score in enumerate(eval_scores):
            step = 1000 * (i + 1)
            rank = float(rng.normal())
            write_checkpoint(config, step, policy_bytes(config, step, fake={"eval": float(score), "rank": rank}))
            service.scan()
            assert service.next_checkpoint()[0] == step
            member = service.process(step, service.checkpoint_dir / f"policy-{step:09d}.safetensors")
            scores[step], rank_scores[step] = float(score), rank
            want = expected_top(scores)
            assert (member is not None) == (step in want)
            index = topk.check_folder(top_dir(config), k=5)
            assert [m["step"] for m in index["members"]] == want
            on_disk = sorted(p.name for p in top_dir(config).iterdir())
            assert on_disk == sorted([topk.policy_file_name(s) for s in want] + ["index.json"])
            best = max(want, key=lambda s: (rank_scores[s], scores[s], -s))
            assert index["best"] == topk.policy_file_name(best)
            assert service.snapshot.best.step == best
            assert [h["step"] for h in index["history"]] == sorted(scores)
        # The member files carry their scores in the policy metadata.
        _, meta = load_policy_bytes((top_dir(config) / index["best"]).read_bytes())
        assert meta.eval_score == pytest.approx(rank_scores[best])
        assert meta.extra["evaluation"]["eval_score"] == pytest.approx(scores[best])
        assert meta.training_steps == best
        # Ties: 9.0 twice and 7.0 twice; the earlier checkpoint of a tie wins membership.
        assert service.stats()["top_count"] == 5 and service.stats()["evaluations"] == len(eval_scores)


def test_eval_every_spacing_and_restart_continues(tmp_path):
    config = tiny_config(tmp_path)
    steps = [1000, 1500, 2000, 2600, 3000, 3999, 4000]
    for s in steps:
        write_checkpoint(config, s, policy_bytes(config, s, fake={"eval": s / 1000, "rank": 0.0}))
    evaluated = []
    with EvaluatorService(config, score_fn=fake_score, log_episodes=False, newest_first=False) as service:
        service.load()
        nxt = service.next_checkpoint()
        evaluated.append(nxt[0])
        service.process(*nxt)
        service.process(*service.next_checkpoint())  # 2000: 1500 is too close to 1000
        evaluated.append(service.top.last_step)
    # A restarted evaluator reloads the index and goes on from the last evaluated step.
    with EvaluatorService(config, score_fn=fake_score, log_episodes=False, newest_first=False) as service:
        service.load()
        assert service.top.last_step == 2000
        while (nxt := service.next_checkpoint()) is not None:
            evaluated.append(nxt[0])
            service.process(*nxt)
        assert service.counters.skipped == 1  # 3999, too close to 3000 (2600 is not even queued)
    assert evaluated == [1000, 2000, 3000, 4000]


def test_the_service_follows_the_front_of_training(tmp_path):
    """A live evaluator behind training takes the newest checkpoint and skips the backlog."""
    config = tiny_config(tmp_path)
    with EvaluatorService(config, score_fn=fake_score, log_episodes=False, scan_every=1e9) as service:
        service.load()
        write_checkpoint(config, 1000, policy_bytes(config, 1000, fake={"eval": 1.0, "rank": 1.0}))
        service.scan()
        service.process(*service.next_checkpoint())
        for s in (2000, 3000, 4000, 4500):
            write_checkpoint(config, s, policy_bytes(config, s, fake={"eval": 1.0, "rank": 1.0}))
        service.scan()
        assert service.next_checkpoint()[0] == 4500
        assert service.counters.skipped == 3 and service.next_checkpoint() is None


def test_an_announcement_never_overtakes_older_unseen_checkpoints(tmp_path):
    """An evaluator that connects late misses announcements; the folder still has the files.
    When a newer announcement arrives, the older files must be evaluated first (else the
    eval_every spacing would skip them for good)."""
    from forcegrasp.protocol import Checkpoint, encode_checkpoint

    config = tiny_config(tmp_path)
    with EvaluatorService(config, score_fn=fake_score, log_episodes=False, scan_every=1e9,
                          newest_first=False) as service:
        service.load()  # the folder is still empty
        for s in (1000, 2000, 3000):
            write_checkpoint(config, s, policy_bytes(config, s, fake={"eval": 1.0, "rank": 1.0}))
        service.on_announcement(encode_checkpoint(Checkpoint(3000, "/learner/host/policy-000003000.safetensors")))
        order = []
        while service.poll_once():
            order.append(service.top.last_step)
        assert order == [1000, 2000, 3000]
        # Junk and a path naming another file than its step are refused, not followed.
        service.on_announcement(b"junk")
        service.on_announcement(encode_checkpoint(Checkpoint(9000, "policy-000004000.safetensors")))
        assert not service.poll_once()
        assert service.rejects.counts() == {"malformed": 1, "bad_field": 1}


def test_reload_drops_corrupt_or_missing_members_and_cleans_leftovers(tmp_path, caplog):
    config = tiny_config(tmp_path)
    ranks = {1000: 5.0, 2000: 9.0, 3000: 1.0, 4000: 7.0}
    with EvaluatorService(config, score_fn=fake_score, log_episodes=False) as service:
        service.load()
        for s, r in ranks.items():
            path = write_checkpoint(config, s, policy_bytes(config, s, fake={"eval": s / 1000, "rank": r}))
            service.process(s, path)
        assert service.top.best.step == 2000
    folder = top_dir(config)
    data = bytearray((folder / "policy-000002000.safetensors").read_bytes())
    data[-5] ^= 0xFF  # the best's weights silently damaged on disk
    (folder / "policy-000002000.safetensors").write_bytes(bytes(data))
    (folder / "policy-000004000.safetensors").unlink()
    (folder / "policy-000009000.safetensors").write_bytes(b"a save interrupted before its index")
    (folder / ".index.json.abc.tmp").write_text("{")
    with caplog.at_level(logging.WARNING, logger="forcegrasp.evaluator"):
        with EvaluatorService(config, score_fn=fake_score, log_episodes=False) as service:
            service.load()
            assert sorted(m.step for m in service.top.members) == [1000, 3000]
            assert service.top.best.step == 1000  # best recomputed among the survivors
            assert service.snapshot.best.step == 1000
    assert "policy-000002000.safetensors" in caplog.text and "SHA-256" in caplog.text
    assert "policy-000004000.safetensors" in caplog.text
    index = topk.check_folder(folder, k=5)
    assert sorted(p.name for p in folder.iterdir()) == ["index.json", "policy-000001000.safetensors",
                                                        "policy-000003000.safetensors"]
    assert index["last_step"] == 4000  # the history survives: those steps are not evaluated again
    # An unreadable index is moved aside (kept for a person), and the evaluator starts empty.
    (folder / "index.json").write_text("{ not json")
    with EvaluatorService(config, score_fn=fake_score, log_episodes=False) as service:
        service.load()
        assert service.top.members == [] and service.snapshot.best is None
    assert list(folder.glob("index.json.bad-*"))


def test_bad_checkpoints_are_rejected_and_the_service_goes_on(tmp_path):
    config = tiny_config(tmp_path)
    write_checkpoint(config, 1000, b"\x00" * 100)
    mug = tiny_config(tmp_path, **{"env.object": "mug"})
    write_checkpoint(config, 2000, policy_bytes(mug, 2000, fake={"eval": 1.0, "rank": 1.0}))
    no_ff = tiny_config(tmp_path, **{"env.force_feedback": "false"})
    write_checkpoint(config, 3000, policy_bytes(no_ff, 3000, fake={"eval": 1.0, "rank": 1.0}))
    write_checkpoint(config, 4000, policy_bytes(config, 4000, fake={"eval": 1.0, "rank": 1.0}))
    with EvaluatorService(config, score_fn=fake_score, log_episodes=False, newest_first=False) as service:
        service.load()
        while (nxt := service.next_checkpoint()) is not None:
            service.process(*nxt)
        assert service.counters.bad_checkpoints == 3
        assert [m.step for m in service.top.members] == [4000]
        assert service.failed == {1000, 2000, 3000}
        service.scan()
        assert service.next_checkpoint() is None  # rejected ones are not retried in a loop


def test_real_rollouts_rank_constant_speed_policies(tmp_path):
    """The default scorer (real episodes) on the known-score family: slower is better."""
    config = tiny_config(tmp_path, **{"evaluator.top_k": 2})
    speeds = {1000: 0.6, 2000: 0.1, 3000: 0.9, 4000: 0.3}
    with EvaluatorService(config, log_episodes=False) as service:
        service.load()
        for step, speed in speeds.items():
            service.process(step, write_checkpoint(config, step, policy_bytes(config, step, speed)))
        scores = {h["step"]: h["score"] for h in service.top.history}
        assert sorted(scores, key=scores.get) == [3000, 1000, 4000, 2000]
        assert [m.step for m in service.top.members] == [2000, 4000]
        assert service.top.best.step == 2000
        assert all(m.rank_episodes == 3 and m.episodes == 2 for m in service.top.members)


# --------------------------------------------------------------------------------------------
# MCAP episode logs and replay
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def logged_episode(tmp_path_factory):
    """One real episode with MCAP logging, and the same episode recorded by hand without it."""
    from forcegrasp.env import FunctionalGraspEnv

    out = tmp_path_factory.mktemp("mcap")
    env = FunctionalGraspEnv("camera", max_steps=15)
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, (15, 7)).astype(np.float32)
    state = {"t": 0}

    def policy(obs):
        a = actions[state["t"] % 15]
        state["t"] += 1
        return a

    place = placements(0, 1, 0.02)
    result = evaluate(env, policy, place, log_dir=out, log_prefix="eval", log_metadata={"checkpoint_step": 42})
    # Replay the same actions without logging: the ground truth for the logged numbers.
    obs, info = env.reset(seed=place[0].seed, options={"offset": place[0].offset})
    truth = {"qpos": [env.data.qpos[env.ix.all_qpos].copy()], "obj": [env.data.xpos[env.ix.object_body].copy()],
             "effort": [env.data.actuator_force[np.r_[env.ix.base_act, env.ix.hand_act]].copy()], "reward": [],
             "r_c": []}
    for t in range(result.steps):
        obs, r, term, trunc, info = env.step(actions[t])
        truth["qpos"].append(env.data.qpos[env.ix.all_qpos].copy())
        truth["obj"].append(env.data.xpos[env.ix.object_body].copy())
        truth["effort"].append(env.data.actuator_force[np.r_[env.ix.base_act, env.ix.hand_act]].copy())
        truth["reward"].append(r)
        truth["r_c"].append(info["r_c"])
    env.close()
    return out / "eval-000.mcap", result, {k: np.array(v) for k, v in truth.items()}


def test_mcap_file_has_the_expected_channels_schemas_and_step_counts(logged_episode):
    from mcap.reader import make_reader

    path, result, _ = logged_episode
    steps = result.steps
    assert steps == 15 or result.returns  # the episode may end early on failure: counts follow it
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        channels = {c.topic: c for c in summary.channels.values()}
        schemas = {s.id: s for s in summary.schemas.values()}
        counts = summary.statistics.channel_message_counts
        assert {t: (schemas[c.schema_id].name, schemas[c.schema_id].encoding, c.message_encoding)
                for t, c in channels.items()} == {
            "/scene": ("foxglove.SceneUpdate", "jsonschema", "json"),
            "/tf": ("foxglove.FrameTransforms", "jsonschema", "json"),
            "/joint_states": ("foxglove.JointStates", "jsonschema", "json"),
            "/command": ("forcegrasp.Command", "jsonschema", "json"),
            "/reward": ("forcegrasp.RewardTerms", "jsonschema", "json"),
            "/outcome": ("forcegrasp.EpisodeOutcome", "jsonschema", "json"),
        }
        by_topic = {t: counts[c.id] for t, c in channels.items()}
        assert by_topic == {"/scene": 1, "/outcome": 1, "/tf": steps + 1, "/joint_states": steps + 1,
                            "/command": steps + 1, "/reward": steps + 1}
        assert all(c.compression == "zstd" for c in summary.chunk_indexes)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}["forcegrasp.episode"]
    assert meta["object"] == "camera" and meta["checkpoint_step"] == "42" and meta["stream"] == "eval"
    # Message times are sim time: 20 ms apart.
    with open(path, "rb") as f:
        times = [m.log_time for _, c, m in make_reader(f).iter_messages(topics=["/joint_states"])]
    assert np.all(np.diff(times) == 20_000_000)


def test_mcap_messages_match_the_simulation_and_their_schemas(logged_episode):
    from forcegrasp.mcap_log import SCHEMAS, TOPIC_SCHEMAS, read_episode

    path, result, truth = logged_episode
    log = read_episode(path)
    assert np.abs(log.qpos() - truth["qpos"]).max() <= 5.01e-7  # 6 decimals
    assert np.abs(log.object_poses()[:, :3] - truth["obj"]).max() <= 5.01e-7
    efforts = np.array([[j["effort"] for j in m["joints"]] for m in log.messages["/joint_states"]])
    assert np.abs(efforts - truth["effort"]).max() <= 5.01e-7
    rewards = log.messages["/reward"]
    assert [r["step"] for r in rewards] == list(range(result.steps + 1))
    assert np.allclose([r["reward"] for r in rewards[1:]], truth["reward"])
    assert np.allclose([r["r_c"] for r in rewards[1:]], truth["r_c"])
    assert rewards[-1]["return"] == pytest.approx(result.score)
    outcome = log.messages["/outcome"][0]
    assert outcome["return"] == pytest.approx(result.score) and outcome["length"] == result.steps
    actions = np.array([m["action"] for m in log.messages["/command"][1:]])
    assert actions.shape == (result.steps, 7) and np.abs(actions).max() <= 0.3 + 1e-6
    targets = np.array([m["targets"] for m in log.messages["/command"]])
    assert targets.shape == (result.steps + 1, 30)
    frames = {t["child_frame_id"] for t in log.messages["/tf"][0]["transforms"]}
    assert {"object", "palm_center", "hand/forearm", "hand/ffdistal", "hand/thdistal"} <= frames
    entities = {e["id"]: e for e in log.messages["/scene"][0]["entities"]}
    assert entities["object"]["frame_locked"] and (entities["object"]["cubes"] or entities["object"]["cylinders"])
    assert set(entities) <= frames  # every entity hangs on a frame that /tf moves
    jsonschema = pytest.importorskip("jsonschema")
    for topic, messages in log.messages.items():
        validator = jsonschema.Draft7Validator(SCHEMAS[TOPIC_SCHEMAS[topic]])
        for message in messages:
            validator.validate(message)


def test_fixed_width_numbers_are_valid_json_to_six_decimals():
    from forcegrasp.mcap_log import FLOAT_WIDTH, fixed_chars

    values = np.concatenate([[0.0, -0.0, 1e-7, -4e-7, -6e-7, 0.5, -0.5, 123.4567894, -999.9999994, 999.9999994],
                             np.random.default_rng(0).uniform(-999, 999, 2000)])
    chars = fixed_chars(values)
    assert chars.shape == (len(values), FLOAT_WIDTH)
    fields = [bytes(row).decode() for row in chars]
    parsed = json.loads("[" + ",".join(fields) + "]")
    assert np.abs(np.array(parsed) - values).max() <= 5.0001e-7
    assert fields[3] == "   0.000000 " and fields[4] == "  -0.000001 " and fields[8] == "-999.999999 "
    assert not any("-0.000000" in f for f in fields)


def test_out_of_range_and_nonfinite_steps_are_still_valid_json(tmp_path):
    from mcap.reader import make_reader

    from forcegrasp.env import FunctionalGraspEnv
    from forcegrasp.mcap_log import EpisodeLogger

    env = FunctionalGraspEnv("camera", max_steps=5)
    obs, info = env.reset(seed=0)
    log = EpisodeLogger(tmp_path / "odd.mcap", env, backend="mcap")
    log.begin(0, info)
    for value in (np.nan, 5000.0, None):
        obs, r, term, trunc, info = env.step(np.zeros(7))
        if value is not None:
            env.data.actuator_force[env.ix.hand_act[0]] = value  # as if the simulation had diverged
        log.step(np.zeros(7), r, info)
    log.end(1.0, 3, False, None)

    def strict(text):
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))

    with open(tmp_path / "odd.mcap", "rb") as f:
        joints = [strict(m.data)["joints"] for _, _, m in make_reader(f).iter_messages(topics=["/joint_states"])]
    effort = [next(j["effort"] for j in js if j["name"] == "WRJ1") for js in joints]
    assert effort[1] is None and effort[2] == 5000.0 and isinstance(effort[3], float)
    env.close()


def test_logging_does_not_change_the_episode(tmp_path):
    from forcegrasp.env import FunctionalGraspEnv

    env = FunctionalGraspEnv("camera", max_steps=10)
    policy = lambda obs: np.tanh(obs[:7] * 0.01).astype(np.float32)  # noqa: E731 (reacts to the state)
    places = placements(1, 2, 0.02)
    off = evaluate(env, policy, places)
    backends = ["mcap"] + (["sdk"] if importlib.util.find_spec("foxglove") else [])
    for backend in backends:
        on = evaluate(env, policy, places, log_dir=tmp_path / backend, logger_backend=backend)
        assert off.returns == on.returns
        assert sorted(p.name for p in (tmp_path / backend).iterdir()) == ["ep-000.mcap", "ep-001.mcap"]
        from forcegrasp.mcap_log import read_episode

        log = read_episode(tmp_path / backend / "ep-001.mcap")
        assert log.messages["/outcome"][0]["return"] == pytest.approx(on.returns[1])


def test_replay_renders_an_image_strip(logged_episode, tmp_path, capsys):
    from PIL import Image

    from forcegrasp.cli import main

    path, result, _ = logged_episode
    out = tmp_path / "strip.png"
    assert main(["replay", str(path), "--out", str(out), "--frames", "4", "--width", "160", "--height", "120"]) == 0
    image = np.asarray(Image.open(out))
    assert image.shape == (120, 4 * 160, 3)
    tiles = image.reshape(120, 4, 160, 3).transpose(1, 0, 2, 3)
    assert tiles.std() > 10 and not np.array_equal(tiles[0], tiles[-1])  # a scene, and it moves
    video = tmp_path / "video.mp4"  # always an MP4: imageio-ffmpeg is a dependency (tests/test_video.py reads them)
    assert main(["replay", str(path), "--out", str(video), "--stride", "5", "--width", "96", "--height", "64"]) == 0
    assert video.stat().st_size > 1000 and not video.with_suffix(".png").exists()
    not_mcap = tmp_path / "junk.mcap"
    not_mcap.write_bytes(b"not an mcap file")
    assert main(["replay", str(not_mcap)]) == 1
    assert "not a readable MCAP file" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# The ``best`` message and the HTTP server, in process
# --------------------------------------------------------------------------------------------

def make_best(config, step=3000, speed=0.2) -> BestPolicy:
    data = policy_bytes(config, step, speed)
    return BestPolicy(run=config.run.name, step=step, score=12.5, success_rate=0.5, episodes=3, eval_score=13.0,
                      eval_success_rate=0.5, eval_episodes=2, object="camera", force_feedback=True,
                      policy_version=3, sha256=hashlib.sha256(data).hexdigest(), policy=data, time=1.0)


def test_best_message_round_trip_and_rejections(tmp_path):
    import msgpack

    config = tiny_config(tmp_path)
    best = make_best(config)
    assert decode_best(encode_best(best)) == best
    good = msgpack.unpackb(encode_best(best))

    def variant(**change):
        msg = {**good, **change}
        return msgpack.packb({k: v for k, v in msg.items() if v is not None}, use_bin_type=True)

    bad = {
        "junk": b"\x00garbage",
        "type": variant(t="checkpoint"),
        "version": variant(v=2),
        "missing": variant(policy=None),
        "extra": variant(surprise=1),
        "sha": variant(sha256="0" * 64),
        "policy": variant(policy=b"not a policy file", sha256=hashlib.sha256(b"not a policy file").hexdigest()),
        "object": variant(object="mug"),
        "ff": variant(force_feedback=1),
        "nan": variant(score=float("nan")),
    }
    for name, payload in bad.items():
        with pytest.raises(ProtocolError):
            decode_best(payload)


@pytest.fixture()
def http_server(tmp_path):
    config = tiny_config(tmp_path)
    state = {"snap": Snapshot.build(config.run.name, None, {"members": []})}
    server = EvaluatorHTTPServer("127.0.0.1", 0, lambda: state["snap"]).start()
    try:
        yield config, server, state
    finally:
        server.stop()


def request(port, method, path, body=None):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.putrequest(method, path, skip_accept_encoding=True)
        conn.putheader("Content-Length", str(len(body or b"")))
        conn.endheaders(body)
        resp = conn.getresponse()
        return resp.status, dict(resp.getheaders()), resp.read()
    finally:
        conn.close()


def test_http_serves_best_and_top_and_refuses_everything_else(http_server):
    config, server, state = http_server
    port = server.port
    status, _, body = request(port, "GET", "/best")
    assert status == 503 and "no checkpoint evaluated yet" in json.loads(body)["error"]
    best = make_best(config)
    state["snap"] = Snapshot.build(config.run.name, best, {"members": [{"step": best.step}]})
    status, headers, body = request(port, "GET", "/best")
    assert status == 200 and headers["Content-Type"] == "application/json"
    meta = json.loads(body)
    assert meta["step"] == 3000 and meta["sha256"] == best.sha256 and meta["object"] == "camera"
    assert meta["force_feedback"] is True and meta["score"] == 12.5
    status, headers, body = request(port, "GET", "/best/policy")
    assert status == 200 and body == best.policy and headers["X-ForceGrasp-Sha256"] == best.sha256
    assert "attachment" in headers["Content-Disposition"]
    status, headers, body = request(port, "HEAD", "/best/policy")
    assert status == 200 and body == b"" and int(headers["Content-Length"]) == len(best.policy)
    assert json.loads(request(port, "GET", "/top")[2]) == {"members": [{"step": 3000}]}
    assert request(port, "GET", f"/best?run={config.run.name}")[0] == 200

    refusals = {
        ("GET", "/etc/passwd"): 404, ("GET", "/best/../top"): 404, ("GET", "/../../etc/passwd"): 404,
        ("GET", "/best/..%2f..%2fetc%2fpasswd"): 404, ("GET", "/%2e%2e/index.json"): 404,
        ("GET", "//etc/passwd"): 404, ("GET", "/top\\..\\index.json"): 404, ("GET", "/index.json"): 404,
        ("GET", "/best/policy/x"): 404, ("GET", "http://evil/best"): 404, ("GET", "/best?run=other"): 404,
        ("GET", "/best?file=../../x"): 400, ("GET", "/best?run=a&run=b"): 400, ("GET", "/best?%zz"): 400,
        ("POST", "/best"): 405, ("PUT", "/best/policy"): 405, ("DELETE", "/top"): 405, ("PATCH", "/"): 405,
        ("OPTIONS", "/best"): 405, ("BREW", "/best"): 405,
    }
    for (method, path), want in refusals.items():
        status, headers, body = request(port, method, path, body=b"x" if method in ("POST", "PUT") else None)
        assert status == want, (method, path, status, body)
        error = json.loads(body)["error"]
        assert error and "root:" not in error
        if want == 405:
            assert headers["Allow"] == "GET, HEAD"
    assert "unknown run 'other'" in json.loads(request(port, "GET", "/best?run=other")[2])["error"]
    # Still serving after all that.
    assert request(port, "GET", "/best/policy")[2] == best.policy
    # The client checks what it downloads.
    assert fetch_best_http(f"http://127.0.0.1:{port}").policy == best.policy
    with pytest.raises(BestFetchError, match="unknown run 'nope'"):
        fetch_best_http(f"http://127.0.0.1:{port}", run="nope")
    with pytest.raises(BestFetchError, match="cannot connect"):
        fetch_best_http("http://127.0.0.1:9", timeout=2)


def test_http_bounds_bodies_rates_and_connections(tmp_path, monkeypatch):
    """A body is refused, a flood of requests from one address is cut to its rate, and idle
    connections past the limit are closed without taking a thread; service resumes after."""
    import socket
    import time

    from forcegrasp_evaluator import endpoint

    monkeypatch.setattr(endpoint, "MAX_CONNECTIONS", 4)
    # A slow refill: a flood slowed down by a busy machine cannot earn its tokens back mid-flood.
    monkeypatch.setattr(endpoint, "RATE_PER_S", 2.0)
    monkeypatch.setattr(endpoint, "BURST", 10)
    config = tiny_config(tmp_path)
    snap = Snapshot.build(config.run.name, None, {"members": []})
    server = EvaluatorHTTPServer("127.0.0.1", 0, lambda: snap).start()
    try:
        port = server.port
        status, _, body = request(port, "GET", "/top", body=b"x" * 100)
        assert status == 413 and "no body" in json.loads(body)["error"]
        replies = [request(port, "GET", "/top") for _ in range(endpoint.BURST + 20)]
        statuses = [status for status, _, _ in replies]
        # The 413 above took one token; the rest of the burst is served whole, then 429s.
        assert statuses[:endpoint.BURST - 1] == [200] * (endpoint.BURST - 1), statuses
        assert statuses.count(429) >= 15, statuses
        assert all(headers["Retry-After"] == "1" for status, headers, _ in replies if status == 429)
        time.sleep(1.0)
        assert request(port, "GET", "/top")[0] == 200  # tokens came back
        idle = [socket.create_connection(("127.0.0.1", port)) for _ in range(4)]  # hold every slot
        try:
            deadline = time.monotonic() + 10  # a busy machine may accept them late
            while server.connections < 4 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert server.connections == 4, f"{server.connections} of the 4 idle connections hold a slot"
            with pytest.raises((ConnectionError, http.client.HTTPException, OSError)):
                request(port, "GET", "/top")
        finally:
            for sock in idle:
                sock.close()
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            try:
                if request(port, "GET", "/top")[0] == 200:
                    break
            except (ConnectionError, http.client.HTTPException, OSError):
                time.sleep(0.2)
        else:
            raise AssertionError("the server did not recover after the idle connections closed")
        assert server.requests_by_status["413"] == 1 and server.requests_by_status["503"] >= 1
    finally:
        server.stop()


@pytest.mark.parametrize("keep", ["top", "all"])
def test_episode_logs_are_kept_for_the_top_k_and_the_latest(tmp_path, keep):
    """Real rollouts and MCAP files: with keep_episode_logs="top" the logs of a checkpoint go once
    it is neither in the top k nor the latest evaluated; with "all" every log stays."""
    config = tiny_config(tmp_path, **{"evaluator.top_k": 2, "evaluator.keep_episode_logs": keep})
    steps = [1000, 2000, 3000, 4000, 5000]
    for i, s in enumerate(steps):  # different constant actions: different scores
        write_checkpoint(config, s, policy_bytes(config, s, speed=[0.0, 0.9, 0.3, 0.6, 0.1][i]))
    with EvaluatorService(config, newest_first=False) as service:
        service.load()
        while (nxt := service.next_checkpoint()) is not None:
            service.process(*nxt)
            logged = sorted(int(p.name) for p in service.episodes_dir.iterdir())
            assert all(any((service.episodes_dir / f"{s:09d}").glob("*.mcap")) for s in logged)
            seen = [s for s in steps if s <= nxt[0]]
            if keep == "all":
                assert logged == seen
            else:
                assert logged == sorted({m.step for m in service.top.members} | {nxt[0]})
        assert service.stats()["pruned_logs"] == (0 if keep == "all" else len(steps) - len(logged))
    if keep == "top":
        assert len(logged) < len(steps)  # something was pruned


def test_changed_placements_rescore_the_top_k(tmp_path, monkeypatch):
    """Stored scores are only comparable on the same placements: if the way placements are drawn
    changes (here: every offset shifted, with the same config), a restart re-scores the members."""
    import forcegrasp.ranking as ranking_module

    config = tiny_config(tmp_path)
    for s in (1000, 2000):
        write_checkpoint(config, s, policy_bytes(config, s, fake={"eval": s / 1000, "rank": 0.0}))
    with EvaluatorService(config, score_fn=fake_score, log_episodes=False, newest_first=False) as service:
        service.load()
        while (nxt := service.next_checkpoint()) is not None:
            service.process(*nxt)
        assert service.counters.rank_evaluations == 2
    with EvaluatorService(config, score_fn=fake_score, log_episodes=False) as service:
        service.load()  # same placements: the stored scores stand
        assert service.counters.rank_evaluations == 0
    original = ranking_module.placements
    shifted = lambda *a, **k: [dataclasses.replace(p, offset=(p.offset[0] * 0.5, p.offset[1])) for p in original(*a, **k)]
    monkeypatch.setattr(ranking_module, "placements", shifted)
    with EvaluatorService(config, score_fn=fake_score, log_episodes=False) as service:
        service.load()
        assert service.counters.rank_evaluations == 2  # both members scored again
        assert [m.step for m in service.top.members] == [2000, 1000]


def test_once_scores_a_finished_run_and_exits(tmp_path, capsys):
    """`forcegrasp evaluator --once`: evaluate what is on disk, print the top k, exit (no network)."""
    from forcegrasp_evaluator.evaluator import main

    config = tiny_config(tmp_path, **{"evaluator.top_k": 2})
    for i, s in enumerate((1000, 2000, 3000)):
        write_checkpoint(config, s, policy_bytes(config, s, speed=[0.0, 0.8, 0.4][i]))
    overrides = [f"run.name={config.run.name}", f"run.output_dir={config.run.output_dir}", "env.object=camera",
                 "env.max_steps=20", "evaluator.eval_every=1000", "evaluator.eval_episodes=2",
                 "evaluator.final_rank_episodes=3", "evaluator.top_k=2", "evaluator.http_port=0"]
    assert main(["--once", "--no-mcap", *[a for o in overrides for a in ("--set", o)]]) == 0
    top = json.loads(capsys.readouterr().out)
    assert top["evaluations"] == 3 and len(top["members"]) == 2
    assert top["members"] == topk.check_folder(top_dir(config), k=2)["members"]


def test_cpu_budget_rests_to_its_share():
    """The evaluator's CPU budget: after 3 CPU-seconds in 4 wall-seconds at a 0.5 share it must rest
    2 s (6 s of wall-clock for 3 of CPU); within the share it does not rest; 1.0 never rests."""
    from forcegrasp_evaluator.evaluator import CpuBudget

    now = {"wall": 100.0, "cpu": 10.0}
    budget = CpuBudget(0.5, clock=lambda: now["wall"], cpu_clock=lambda: now["cpu"])
    now.update(wall=104.0, cpu=13.0)
    assert budget.share() == pytest.approx(0.75) and budget.rest() == pytest.approx(2.0)
    now.update(wall=106.0)
    assert budget.rest() == pytest.approx(0.0) and budget.share() == pytest.approx(0.5)
    unbounded = CpuBudget(1.0, clock=lambda: now["wall"], cpu_clock=lambda: now["cpu"])
    now.update(cpu=30.0)
    assert unbounded.rest() == 0.0


def test_mixed_score_is_the_mean_of_the_condition_scores(tmp_path):
    """Several test conditions: each is scored on its own placements (its env's jitter), the
    checkpoint's score and success are the plain means of the conditions' (a hand-made example),
    and the member, its file and the /top view say under which condition each figure was made."""
    config = tiny_config(tmp_path, **{"evaluator.conditions": '["5x", "1x_3cm", "jitter_3cm"]'})
    made = {"5x": (10.0, 1.0), "1x_3cm": (4.0, 0.5), "jitter_3cm": (1.0, 0.0)}
    seen = []

    def score(policy, weights, meta, places, kind, step, condition=None):
        seen.append((kind, condition, len(places)))
        value, success = made[condition]
        return EvalResult(score=value + (0.5 if kind == "rank" else 0.0), success_rate=success, episodes=len(places))

    with EvaluatorService(config, score_fn=score, log_episodes=False) as service:
        assert {c: service._ensure_env(c).jitter for c in made} == {"5x": 0.02, "1x_3cm": 0.02, "jitter_3cm": 0.03}
        assert service._ensure_env("1x_3cm").mass_scale == 1.0 and service._ensure_env("1x_3cm").object_tolerance == 0.03
        service.load()
        write_checkpoint(config, 1000, policy_bytes(config, 1000))
        service.scan()
        member = service.process(*service.next_checkpoint())
    assert sorted(seen) == sorted([("eval", c, 2) for c in made] + [("rank", c, 3) for c in made])
    assert member.score == pytest.approx(5.0) and member.success_rate == pytest.approx(0.5)
    assert member.rank_score == pytest.approx(5.5) and member.episodes == 6 and member.rank_episodes == 9
    assert {c: v["score"] for c, v in member.conditions.items()} == {"5x": 10.5, "1x_3cm": 4.5, "jitter_3cm": 1.5}
    index = topk.check_folder(top_dir(config), k=5)
    assert index["protocol"]["conditions"] == list(made) and index["members"][0]["conditions"]["1x_3cm"]["success_rate"] == 0.5
    assert index["history"][0]["conditions"]["5x"]["score"] == 10.0
    _, meta = load_policy_bytes((top_dir(config) / index["best"]).read_bytes())
    assert meta.extra["evaluation"]["rank_conditions"]["jitter_3cm"]["success_rate"] == 0.0
