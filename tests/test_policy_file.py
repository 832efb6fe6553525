"""Policy files and the deployable Policy: round trips, clear errors, no pickle anywhere."""

import json
import os
import pickle
import struct

import numpy as np
import pytest
import torch

from forcegrasp.policy import Actor, Policy
from forcegrasp.policy_file import (
    FORMAT_VERSION,
    METADATA_KEY,
    PolicyFileError,
    PolicyMetadata,
    atomic_write,
    load_policy_file,
    save_policy_file,
)
from forcegrasp.sac import SAC, SACConfig

OBS_LAYOUT = [("joint_pos", 30), ("joint_vel", 30), ("object_pose", 7), ("fingertip_force", 5), ("grasp_target", 5)]
ACTION_LAYOUT = [("wrist", 2), ("fingers", 5)]


def metadata(**overrides) -> PolicyMetadata:
    fields = dict(obs_layout=OBS_LAYOUT, action_layout=ACTION_LAYOUT, hidden=(32, 32), object_name="mug",
                  force_feedback=True, training_steps=12345, eval_score=0.75,
                  action_low=[-1.0] * 7, action_high=[2.0] * 7, extra={"run": "abc"})
    fields.update(overrides)
    return PolicyMetadata(**fields)


@pytest.fixture
def policy() -> Policy:
    torch.manual_seed(0)
    return Policy.from_actor(Actor(77, 7, hidden=(32, 32)), metadata(), seed=0)


@pytest.fixture
def saved(tmp_path, policy):
    return policy.save(tmp_path / "mug.policy")


def obs_batch(n=5, seed=0):
    return np.random.default_rng(seed).standard_normal((n, 77)).astype(np.float32)


def rewrite_header(path, edit):
    """Re-encode a policy file after `edit(header_dict)`, keeping the tensor bytes."""
    data = path.read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + n])
    edit(header)
    raw = json.dumps(header).encode()
    path.write_bytes(struct.pack("<Q", len(raw)) + raw + data[8 + n :])


def test_round_trip_keeps_weights_metadata_and_actions(saved, policy):
    loaded = Policy.load(saved)
    assert loaded.metadata == policy.metadata
    assert loaded.metadata.obs_dim == 77 and loaded.metadata.act_dim == 7
    for k, v in policy.weights().items():
        np.testing.assert_array_equal(loaded.weights()[k], v)
    np.testing.assert_array_equal(loaded(obs_batch()), policy(obs_batch()))


def test_bytes_and_flat_weights_round_trip(policy):
    again = Policy.from_bytes(policy.to_bytes())
    np.testing.assert_array_equal(again(obs_batch()), policy(obs_batch()))
    weights = policy.weights()
    assert all(isinstance(v, np.ndarray) and v.dtype == np.float32 for v in weights.values())
    raw = {k: v.tobytes() for k, v in weights.items()}  # what a network layer would ship
    shapes = {k: v.shape for k, v in weights.items()}
    rebuilt = Policy.from_weights({k: np.frombuffer(b, np.float32).reshape(shapes[k]) for k, b in raw.items()},
                                  policy.metadata)
    np.testing.assert_array_equal(rebuilt(obs_batch()), policy(obs_batch()))


def test_policy_from_a_learner_matches_its_deterministic_actions(tmp_path):
    sac = SAC(77, 7, SACConfig(hidden=(32, 32), device="cpu", num_threads=1))
    path = sac.policy(metadata()).save(tmp_path / "p.policy")
    obs = obs_batch()
    np.testing.assert_allclose(Policy.load(path)(obs), sac.act(obs, deterministic=True), rtol=0, atol=1e-6)
    # the saved policy is a copy: further learning does not change it
    with torch.no_grad():
        sac.actor.layers[0].weight.add_(1.0)
    assert not np.allclose(Policy.load(path)(obs), sac.act(obs, deterministic=True))


def test_single_and_batched_observations(policy):
    obs = obs_batch(4)
    single = policy(obs[2])
    assert single.shape == (7,) and single.dtype == np.float32
    np.testing.assert_allclose(single, policy(obs)[2], atol=1e-6)
    assert policy(obs.astype(np.float64)).shape == (4, 7)


def test_sampled_actions_are_random_in_range_and_seedable(policy, saved):
    obs = obs_batch(200)
    a, b = policy(obs, deterministic=False), policy(obs, deterministic=False)
    assert not np.allclose(a, b) and np.all(np.abs(a) <= 1)
    det = policy(obs)
    assert np.abs(a - det).mean() > 1e-3  # exploration noise is there
    np.testing.assert_array_equal(Policy.load(saved, seed=7)(obs, False), Policy.load(saved, seed=7)(obs, False))


def test_bad_observations_are_rejected_clearly(policy):
    with pytest.raises(ValueError, match=r"expects \(77,\)"):
        policy(np.zeros(76))
    with pytest.raises(ValueError, match=r"expects"):
        policy(np.zeros((2, 3, 77)))
    bad = np.zeros(77)
    bad[5] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        policy(bad)
    with pytest.raises(ValueError, match="dtype"):
        policy(np.array(["a"] * 77))


def test_rescale_uses_the_recorded_action_range(policy):
    np.testing.assert_allclose(policy.rescale(np.array([-1.0, 0.0, 1.0, -1, -1, -1, -1])), [-1, 0.5, 2, -1, -1, -1, -1])


def test_file_is_a_single_plain_safetensors_file(saved):
    data = saved.read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + n])
    meta = json.loads(header["__metadata__"][METADATA_KEY])
    assert meta["format_version"] == FORMAT_VERSION and meta["object_name"] == "mug"
    assert meta["obs_layout"][3] == ["fingertip_force", 5] and meta["force_feedback"] is True
    assert header["layers.0.weight"] == {"dtype": "F32", "shape": [32, 77], "data_offsets": header["layers.0.weight"]["data_offsets"]}
    assert os.listdir(saved.parent) == [saved.name]  # no sidecar, no leftover temporary


def test_loading_never_unpickles(saved, monkeypatch):
    def forbidden(*a, **k):
        raise AssertionError("unpickling attempted")

    monkeypatch.setattr(pickle, "loads", forbidden)
    monkeypatch.setattr(pickle, "load", forbidden)
    monkeypatch.setattr(pickle, "Unpickler", forbidden)
    monkeypatch.setattr(torch, "load", forbidden)
    Policy.load(saved)


@pytest.mark.parametrize("keep", [0, 5, 8, 100, -1])
def test_truncated_file(saved, keep):
    data = saved.read_bytes()
    saved.write_bytes(data[:keep] if keep >= 0 else data[:-1])
    with pytest.raises(PolicyFileError, match="truncated"):
        Policy.load(saved)


def test_corrupt_header(saved):
    data = bytearray(saved.read_bytes())
    data[9] = ord("#")  # inside the JSON header
    saved.write_bytes(bytes(data))
    with pytest.raises(PolicyFileError, match="corrupt"):
        Policy.load(saved)


def test_garbage_file(tmp_path):
    path = tmp_path / "x.policy"
    path.write_bytes(os.urandom(4096))
    with pytest.raises(PolicyFileError):
        Policy.load(path)


def test_wrong_version(saved):
    def bump(header):
        meta = json.loads(header["__metadata__"][METADATA_KEY])
        meta["format_version"] = FORMAT_VERSION + 1
        header["__metadata__"][METADATA_KEY] = json.dumps(meta)

    rewrite_header(saved, bump)
    with pytest.raises(PolicyFileError, match=f"version {FORMAT_VERSION + 1} is not supported.*newer ForceGrasp"):
        Policy.load(saved)


@pytest.mark.parametrize("version", [1, 0])
def test_an_older_format_version_is_refused_naming_it_and_how_to_migrate(saved, version):
    """Version 2 requires the action range; a file of an older version is refused, not guessed at."""
    assert FORMAT_VERSION == 2

    def older(header):
        meta = json.loads(header["__metadata__"][METADATA_KEY])
        meta["format_version"] = version
        header["__metadata__"][METADATA_KEY] = json.dumps(meta)

    rewrite_header(saved, older)
    with pytest.raises(PolicyFileError) as err:
        Policy.load(saved)
    message = str(err.value)
    assert f"policy file format version {version} is not supported (this ForceGrasp reads version 2)" in message
    assert "re-save" in message and "action_low/action_high" in message and "train the policy again" in message


def test_version_2_requires_the_action_range(tmp_path, saved):
    for name in ("action_low", "action_high"):
        with pytest.raises(PolicyFileError, match=f"{name} is missing"):
            save_policy_file(tmp_path / "x.policy", Policy.load(saved).weights(), metadata(**{name: None}))

    def drop_range(header):  # a version-2 file without it (written by hand) is refused on reading too
        meta = json.loads(header["__metadata__"][METADATA_KEY])
        meta["action_high"] = None
        header["__metadata__"][METADATA_KEY] = json.dumps(meta)

    rewrite_header(saved, drop_range)
    with pytest.raises(PolicyFileError, match="action_high is missing"):
        Policy.load(saved)
    assert not (tmp_path / "x.policy").exists()


def test_foreign_safetensors_file(tmp_path):
    from safetensors.numpy import save_file

    save_file({"w": np.zeros(3, np.float32)}, str(tmp_path / "other.safetensors"))
    with pytest.raises(PolicyFileError, match="without ForceGrasp policy metadata"):
        Policy.load(tmp_path / "other.safetensors")


def test_metadata_that_does_not_match_the_weights(saved):
    def claim_bigger_observation(header):
        meta = json.loads(header["__metadata__"][METADATA_KEY])
        meta["obs_layout"].append(["extra_sensor", 3])
        header["__metadata__"][METADATA_KEY] = json.dumps(meta)

    rewrite_header(saved, claim_bigger_observation)
    with pytest.raises(PolicyFileError, match=r"'layers.0.weight' has shape \(32, 77\).*needs \(32, 80\)"):
        Policy.load(saved)


def test_saving_mismatched_weights_is_refused(tmp_path, policy):
    weights = policy.weights()
    with pytest.raises(PolicyFileError, match="hidden"):
        save_policy_file(tmp_path / "p.policy", weights, metadata(hidden=(64, 64)))
    del weights["layers.2.bias"]
    with pytest.raises(PolicyFileError, match="missing.*layers.2.bias"):
        save_policy_file(tmp_path / "p.policy", weights, metadata())
    assert not (tmp_path / "p.policy").exists()


def test_non_finite_weights_are_refused(tmp_path, policy):
    weights = policy.weights()
    weights["layers.1.weight"][0, 0] = np.inf
    with pytest.raises(PolicyFileError, match="NaN or inf"):
        save_policy_file(tmp_path / "p.policy", weights, metadata())


def test_inconsistent_metadata_is_refused(tmp_path, policy):
    with pytest.raises(PolicyFileError, match="action_low has 3 entries"):
        save_policy_file(tmp_path / "p.policy", policy.weights(), metadata(action_low=[0.0] * 3))


def test_crash_mid_write_keeps_the_old_file(saved):
    before = saved.read_bytes()
    with pytest.raises(RuntimeError):
        with atomic_write(saved) as f:
            f.write(b"half a policy")
            raise RuntimeError("simulated crash")
    assert saved.read_bytes() == before
    assert os.listdir(saved.parent) == [saved.name]
    load_policy_file(saved)


def test_numpy_inference_samples_the_same_distribution_as_the_torch_actor(policy):
    """The CPU fast path (numpy) and the network it copies (torch) are the same policy."""
    obs = np.repeat(obs_batch(1), 4000, axis=0)
    ours = np.arctanh(np.clip(policy(obs, deterministic=False), -0.999999, 0.999999))
    with torch.no_grad():
        mean, log_std = policy.actor(torch.as_tensor(obs[:1]))
    np.testing.assert_allclose(ours.mean(0), mean[0].numpy(), atol=4 * log_std.exp().max().item() / np.sqrt(4000) + 1e-3)
    np.testing.assert_allclose(ours.std(0), log_std[0].exp().numpy(), rtol=0.1)
    with torch.no_grad():
        torch_det = policy.actor.deterministic(torch.as_tensor(obs[:3])).numpy()
    np.testing.assert_allclose(policy(obs[:3]), torch_det, atol=1e-5)


def test_every_policy_file_in_the_repository_is_of_the_current_version():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    files = sorted((root / "assets" / "policies").glob("*.safetensors")) + sorted((root / "tests" / "data").glob("*.safetensors"))
    assert len(files) >= 13
    for path in files:
        meta = load_policy_file(path)[1]
        assert meta.format_version == FORMAT_VERSION and len(meta.action_high) == meta.act_dim, path
