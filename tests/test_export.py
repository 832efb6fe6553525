"""`forcegrasp export`: every shipped policy as ONNX computes what `Policy` computes, on observations
its own env produces; metadata travels with the model; bad input exits 2 and writes nothing."""

import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from forcegrasp import ASSETS_DIR
from forcegrasp.cli import main as cli
from forcegrasp.env import FunctionalGraspEnv
from forcegrasp.export import INPUT_NAME, OUTPUT_NAME, export_policy, onnx_metadata, policy_to_onnx
from forcegrasp.multi_object import policy_objects
from forcegrasp.policy import OBS_CLIP, Actor, Policy
from forcegrasp.policy_file import METADATA_KEY, load_policy_file

SHIPPED = sorted((ASSETS_DIR / "policies").glob("*.safetensors"))
N_OBS = 1000
TOL = 1e-5


def session(path) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1  # the test shares the cores with training
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def run(sess: ort.InferenceSession, obs: np.ndarray) -> np.ndarray:
    return sess.run([OUTPUT_NAME], {INPUT_NAME: np.asarray(obs, np.float32)})[0]


def recorded_observations(policy: Policy, n: int = N_OBS) -> tuple[np.ndarray, np.ndarray]:
    """``n`` observations the policy sees acting in its own env (episodes seeded 0, 1, ..., a policy
    of several objects on each in turn), and the actions it took on them one at a time."""
    envs = [FunctionalGraspEnv.for_policy(policy.metadata, o) for o in policy_objects(policy.metadata)]
    observations, actions = [], []
    seed = 0
    while len(observations) < n:
        env = envs[seed % len(envs)]
        obs, _ = env.reset(seed=seed)
        seed += 1
        while len(observations) < n:
            action = policy(obs)
            observations.append(obs)
            actions.append(action)
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                break
    for env in envs:
        env.close()
    return np.asarray(observations, np.float32), np.asarray(actions, np.float32)


def test_policies_are_shipped():
    assert len(SHIPPED) >= 12, SHIPPED


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_shipped_policy_exports_and_matches(path, tmp_path):
    policy = Policy.load(path, seed=0)
    meta = policy.metadata
    obs, actions = recorded_observations(policy)
    out = tmp_path / f"{path.stem}.onnx"
    assert cli(["export", str(path), "--onnx", str(out)]) == 0

    # Same deterministic actions as Policy, on the batch and as acted one observation at a time.
    sess = session(out)
    onnx_actions = run(sess, obs)
    assert onnx_actions.shape == (N_OBS, 7) and onnx_actions.dtype == np.float32
    assert np.abs(onnx_actions - policy(obs)).max() <= TOL
    assert np.abs(onnx_actions - actions).max() <= TOL
    assert np.all(np.abs(onnx_actions) <= 1.0)

    # The batch dimension is dynamic: declared symbolic, and any batch size runs.
    model = onnx.load(str(out))
    (inp,), (outp,) = model.graph.input, model.graph.output
    assert [inp.name, outp.name] == [INPUT_NAME, OUTPUT_NAME]
    in_dims, out_dims = inp.type.tensor_type.shape.dim, outp.type.tensor_type.shape.dim
    assert in_dims[0].dim_param and not in_dims[0].dim_value and in_dims[1].dim_value == meta.obs_dim
    assert out_dims[0].dim_param and out_dims[1].dim_value == 7
    for n in (1, 3, 257):
        assert run(sess, obs[:n]).shape == (n, 7)
    np.testing.assert_array_equal(run(sess, obs[:1])[0], run(sess, obs[:3])[0])

    # The metadata round-trips, whole and in its readable keys.
    assert onnx_metadata(out) == meta
    props = {p.key: p.value for p in model.metadata_props}
    assert props[METADATA_KEY] == meta.to_json()
    assert props["object_name"] == meta.object_name  # "" for a policy of several objects, named for its set
    assert "+".join(policy_objects(meta)) == path.stem.split("-")[0]
    assert json.loads(props["force_feedback"]) is meta.force_feedback
    assert [tuple(x) for x in json.loads(props["obs_layout"])] == meta.obs_layout
    assert [tuple(x) for x in json.loads(props["action_layout"])] == meta.action_layout
    assert props["action_units"] == "normalized"
    assert {k for k, _ in sess.get_modelmeta().custom_metadata_map.items()} >= {METADATA_KEY, "object_name"}


def test_scaled_actions_match_policy_rescale(tmp_path):
    path = SHIPPED[0]
    policy = Policy.load(path, seed=0)
    obs = np.random.default_rng(0).normal(0, 1, (64, policy.metadata.obs_dim)).astype(np.float32)
    out = tmp_path / "scaled.onnx"
    assert cli(["export", str(path), "--onnx", str(out), "--scale-actions"]) == 0
    expected = policy.rescale(policy(obs))
    got = run(session(out), obs)
    assert np.abs(got - expected).max() <= 1e-7
    assert np.all(np.abs(got) <= np.asarray(policy.metadata.action_high) + 1e-7)
    assert {p.key: p.value for p in onnx.load(str(out)).metadata_props}["action_units"] == "scaled"


def test_observation_normalisation_is_baked_in(tmp_path):
    """No shipped policy normalises observations; a synthetic one checks that path, clipping included."""
    torch.manual_seed(0)
    path = SHIPPED[0]
    meta = load_policy_file(path)[1]
    meta.obs_norm, meta.hidden = True, (32, 16, 8)
    actor = Actor(meta.obs_dim, meta.act_dim, meta.hidden, obs_norm=True)
    actor.obs_mean.normal_()
    actor.obs_std.uniform_(0.05, 3.0)
    policy = Policy.from_actor(actor, meta, seed=0)
    policy.save(tmp_path / "norm.safetensors")
    export_policy(tmp_path / "norm.safetensors", tmp_path / "norm.onnx")
    obs = np.random.default_rng(1).normal(0, 5, (500, meta.obs_dim)).astype(np.float32)
    normalized = (obs - actor.obs_mean.numpy()) / actor.obs_std.numpy()
    assert (np.abs(normalized) > OBS_CLIP).any()  # the clip is exercised
    assert np.abs(run(session(tmp_path / "norm.onnx"), obs) - policy(obs)).max() <= TOL
    assert onnx_metadata(tmp_path / "norm.onnx") == meta


def test_metadata_without_an_action_range_is_refused():
    """Format version 2 records the action range: metadata without it describes no policy file."""
    weights, meta = load_policy_file(SHIPPED[0])
    meta.action_low = meta.action_high = None
    for scale_actions in (True, False):
        with pytest.raises(ValueError, match="action_low is missing"):
            policy_to_onnx(weights, meta, scale_actions=scale_actions)


def test_bad_input_exits_2_and_writes_nothing(tmp_path, capsys):
    good = SHIPPED[0].read_bytes()
    corrupt = tmp_path / "corrupt.safetensors"
    corrupt.write_bytes(good[: len(good) // 2])
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"not a policy file at all")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    out = out_dir / "policy.onnx"
    cases = [
        (corrupt, out, "truncated or corrupt"),
        (garbage, out, "corrupt"),
        (tmp_path / "missing.safetensors", out, "No such file"),
        (SHIPPED[0], tmp_path / "no-such-folder" / "policy.onnx", "output folder does not exist"),
        (SHIPPED[0], out_dir, "is a folder"),
    ]
    for src, dst, message in cases:
        assert cli(["export", str(src), "--onnx", str(dst)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err and err.count("\n") == 1, err
    assert list(out_dir.iterdir()) == []  # no output, no temporary left behind
    assert not (tmp_path / "no-such-folder").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["corrupt.safetensors", "garbage.safetensors", "out"]
