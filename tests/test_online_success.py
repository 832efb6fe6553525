"""Issue 15: with weights frozen, the success rate a real actor process reports is the policy's.

The fixture is a camera policy (the photographer's-grip label) from the fast recipe's first run
on the new grasp labels (snapshot at step 92,608, 58 % deterministic on 50 held-out placements):
a rate away from 0 and 1, so that a bookkeeping error (episodes counted twice, lost, or mixed
across resets) would show.
"""

from pathlib import Path

from forcegrasp.cli.online_check import offline_successes, online_successes, two_proportion_z

POLICY = Path(__file__).parent / "data" / "camera-screening-policy.safetensors"
EPISODES = 150


def test_frozen_policy_online_and_offline_success_agree():
    online = online_successes(POLICY, EPISODES, envs=8, timeout_s=400)
    offline = offline_successes(POLICY, EPISODES)
    assert len(online) == len(offline) == EPISODES
    k1, k2 = sum(online), sum(offline)
    assert 0 < k2 < EPISODES  # the fixture really sits between 0 and 1
    assert abs(two_proportion_z(k1, EPISODES, k2, EPISODES)) < 2.576, (k1, k2)  # 99 % two-sided


def test_a_multi_object_policy_is_checked_object_by_object(tmp_path):
    """The actor's envs go round a generalist's objects; its episodes come back by object, and the
    offline run plays as many on each."""
    import numpy as np

    from forcegrasp.config import load_config
    from forcegrasp.policy_file import actor_param_shapes, policy_to_bytes
    from forcegrasp.runtime import policy_metadata

    meta = policy_metadata(load_config(env={}, overrides=['env.objects=["camera", "mug"]']), (8,))
    path = tmp_path / "generalist.safetensors"
    path.write_bytes(policy_to_bytes({k: np.full(s, 0.05, np.float32) for k, s in actor_param_shapes(meta).items()},
                                     meta))
    online = online_successes(path, 24, envs=4, timeout_s=300)
    assert set(online) == {"camera", "mug"} and sum(map(len, online.values())) == 24
    assert all(len(v) >= 6 for v in online.values())  # two envs each: both objects really played
    offline = offline_successes(path, {o: len(v) for o, v in online.items()})
    assert {o: len(v) for o, v in offline.items()} == {o: len(v) for o, v in online.items()}
