"""Replay buffer: ring semantics, sampling only written slots, safe snapshots."""

import os
import zipfile

import numpy as np
import pytest

from forcegrasp.replay import ReplayBuffer, ReplaySnapshotError


def rows(start, n, obs_dim=3, act_dim=2):
    """Transitions whose every field encodes its index, so positions can be checked exactly."""
    i = np.arange(start, start + n, dtype=np.float32)
    return (np.repeat(i[:, None], obs_dim, 1), np.repeat(-i[:, None], act_dim, 1), i * 10,
            np.repeat(i[:, None] + 0.5, obs_dim, 1), (i % 2 == 0).astype(np.float32))


def test_batched_insert_wraps_around_and_keeps_newest():
    buf = ReplayBuffer(3, 2, capacity=5)
    buf.add_batch(*rows(0, 3))
    assert len(buf) == 3 and buf.pos == 3
    buf.add_batch(*rows(3, 4))  # 3, 4 fill the end; 5, 6 overwrite slots 0, 1
    assert len(buf) == 5 and buf.pos == 2
    np.testing.assert_array_equal(buf.obs[:, 0], [5, 6, 2, 3, 4])
    np.testing.assert_array_equal(buf.action[:, 1], [-5, -6, -2, -3, -4])
    np.testing.assert_array_equal(buf.reward, [50, 60, 20, 30, 40])
    np.testing.assert_array_equal(buf.next_obs[:, 2], [5.5, 6.5, 2.5, 3.5, 4.5])
    np.testing.assert_array_equal(buf.terminated, [0, 1, 1, 0, 1])
    assert buf.total_added == 7


def test_batch_larger_than_capacity_keeps_only_the_last_rows():
    buf = ReplayBuffer(3, 2, capacity=4)
    buf.add_batch(*rows(0, 1))
    buf.add_batch(*rows(1, 10))  # rows 7..10 survive, written starting at slot 1
    assert len(buf) == 4
    assert sorted(buf.obs[:, 0].tolist()) == [7, 8, 9, 10]
    assert buf.pos == 1 and buf.obs[0, 0] == 10  # newest row just before the write position


def test_single_add_and_shape_validation():
    buf = ReplayBuffer(3, 2, capacity=4)
    buf.add(np.ones(3), np.zeros(2), 1.5, np.ones(3) * 2, True)
    assert len(buf) == 1 and buf.reward[0] == 1.5 and buf.terminated[0] == 1.0
    with pytest.raises(ValueError, match="obs has shape"):
        buf.add_batch(np.ones((2, 4)), np.ones((2, 2)), np.ones(2), np.ones((2, 3)), np.ones(2))


def test_sample_only_returns_written_slots():
    buf = ReplayBuffer(3, 2, capacity=1000)
    buf.add_batch(*rows(1, 7))  # indices 1..7; slots 7.. stay zero and must never be sampled
    batch = buf.sample(4096, np.random.default_rng(0))
    assert batch.obs.shape == (4096, 3) and batch.action.shape == (4096, 2) and batch.reward.shape == (4096,)
    assert set(batch.obs[:, 0].tolist()) == set(range(1, 8))  # uniform: every written slot shows up
    # fields of one sample belong to the same transition
    np.testing.assert_array_equal(batch.reward, batch.obs[:, 0] * 10)
    np.testing.assert_array_equal(batch.next_obs[:, 0], batch.obs[:, 0] + 0.5)
    counts = np.bincount(batch.obs[:, 0].astype(int), minlength=8)[1:]
    assert counts.min() > 4096 / 7 * 0.8  # roughly uniform


def test_sample_from_empty_buffer_fails_clearly():
    with pytest.raises(ValueError, match="empty"):
        ReplayBuffer(3, 2, 4).sample(2, np.random.default_rng(0))


@pytest.mark.parametrize("n", [3, 7])  # partly filled, and wrapped
def test_save_load_round_trip(tmp_path, n):
    buf = ReplayBuffer(3, 2, capacity=5)
    buf.add_batch(*rows(0, n))
    path = buf.save(tmp_path / "replay.npz")
    back = ReplayBuffer.load(path)
    assert (back.capacity, back.pos, back.size, back.total_added) == (buf.capacity, buf.pos, buf.size, buf.total_added)
    for field in ("obs", "action", "reward", "next_obs", "terminated"):
        np.testing.assert_array_equal(getattr(back, field)[: back.size], getattr(buf, field)[: buf.size])
    # and it keeps working as the same ring: the next insert overwrites the same (oldest) slot
    buf.add_batch(*rows(100, 1))
    back.add_batch(*rows(100, 1))
    np.testing.assert_array_equal(back.obs, buf.obs)


def test_load_into_larger_capacity_keeps_fifo_order(tmp_path):
    buf = ReplayBuffer(3, 2, capacity=4)
    buf.add_batch(*rows(0, 6))  # holds 2, 3, 4, 5 with the oldest (2) at slot 2
    back = ReplayBuffer.load(buf.save(tmp_path / "r.npz"), capacity=6)
    np.testing.assert_array_equal(back.obs[:4, 0], [2, 3, 4, 5])
    back.add_batch(*rows(6, 3))  # fills 2 free slots, then evicts the oldest (2)
    assert sorted(back.obs[:, 0].tolist()) == [3, 4, 5, 6, 7, 8]


def test_snapshot_has_no_pickled_objects(tmp_path):
    buf = ReplayBuffer(3, 2, capacity=4)
    buf.add_batch(*rows(0, 2))
    path = buf.save(tmp_path / "r.npz")
    with np.load(path, allow_pickle=False) as z:  # would raise on any object array
        assert set(z.files) == {"obs", "action", "reward", "next_obs", "terminated", "horizon", "header"}
        assert all(z[k].dtype != object for k in z.files)


def test_corrupt_snapshot_gives_clear_error(tmp_path):
    buf = ReplayBuffer(3, 2, capacity=64)
    buf.add_batch(*rows(0, 64))
    path = buf.save(tmp_path / "r.npz")
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("obs.npy")
    data[info.header_offset + info.compress_size // 2 + 100] ^= 0xFF  # flip a byte inside the obs payload
    path.write_bytes(bytes(data))
    with pytest.raises(ReplaySnapshotError, match="corrupt.*CRC"):  # caught by the zip checksum
        ReplayBuffer.load(path)


def test_truncated_snapshot_gives_clear_error(tmp_path):
    buf = ReplayBuffer(3, 2, capacity=64)
    buf.add_batch(*rows(0, 64))
    path = buf.save(tmp_path / "r.npz")
    path.write_bytes(path.read_bytes()[:-300])
    with pytest.raises(ReplaySnapshotError, match="corrupt or truncated"):
        ReplayBuffer.load(path)


def test_foreign_npz_is_rejected(tmp_path):
    np.savez(tmp_path / "other.npz", obs=np.zeros(3))
    with pytest.raises(ReplaySnapshotError, match="not a ForceGrasp replay snapshot"):
        ReplayBuffer.load(tmp_path / "other.npz")


def test_crash_mid_save_leaves_previous_snapshot_intact(tmp_path, monkeypatch):
    path = tmp_path / "r.npz"
    good = ReplayBuffer(3, 2, capacity=8)
    good.add_batch(*rows(0, 5))
    good.save(path)
    before = path.read_bytes()

    newer = ReplayBuffer(3, 2, capacity=8)
    newer.add_batch(*rows(50, 8))
    real_savez = np.savez

    def dies_half_way(f, **arrays):  # writes part of the archive, then "crashes"
        real_savez(f, **{k: arrays[k] for k in list(arrays)[:2]})
        raise KeyboardInterrupt("simulated crash during save")

    monkeypatch.setattr(np, "savez", dies_half_way)
    with pytest.raises(KeyboardInterrupt):
        newer.save(path)
    monkeypatch.undo()

    assert path.read_bytes() == before  # the good snapshot was not replaced
    assert os.listdir(tmp_path) == ["r.npz"]  # and no temporary file is left behind
    back = ReplayBuffer.load(path)
    np.testing.assert_array_equal(back.obs[:5, 0], [0, 1, 2, 3, 4])
