import h5py
import numpy as np
import pytest

from pivla.data.episode import DatasetError, Episode
from pivla.data.hdf5 import read_episodes, write_episodes
from pivla.data.normalize import ActionStats
from pivla.data.read import read_dataset
from pivla.data.samples import (
    ChunkDataset,
    augment_shift,
    fit_norm_stats,
    gae,
    image_store,
    prepare_episode,
    prepare_episodes,
    split_episodes,
    task_balanced_weights,
    weighted_batch_indices,
)
from pivla.data.synthetic import synthetic_episode
from pivla.data.text import WordTokenizer
from pivla.model.config import ModelConfig


def _episode(T=12, seed=0, **kw):
    return synthetic_episode(np.random.default_rng(seed), "left", T=T, size=16, **kw)


def test_write_read_round_trip(tmp_path):
    eps = [_episode(seed=i) for i in range(3)] + [_episode(seed=9, success=False)]
    path = write_episodes(tmp_path / "a.hdf5", eps)
    back = read_episodes(path)
    assert len(back) == 4
    for a, b in zip(eps, back):
        np.testing.assert_array_equal(a.actions, b.actions)
        np.testing.assert_array_equal(a.obs["agentview_rgb"], b.obs["agentview_rgb"])
        assert a.instruction == b.instruction and a.success == b.success
    assert [e.success for e in back] == [True, True, True, False]
    with h5py.File(path) as f:  # official layout
        assert "language_instruction" in f["data"].attrs["problem_info"]
        assert f["data/demo_0/obs/agentview_rgb"].dtype == np.uint8


def test_official_layout_without_extensions_loads(tmp_path):
    """A file as LIBERO writes it: no per-demo instruction/success attributes."""
    ep = _episode()
    with h5py.File(tmp_path / "libero.hdf5", "w") as f:
        g = f.create_group("data")
        g.attrs["problem_info"] = '{"language_instruction": "pick up the bowl"}'
        d = g.create_group("demo_0")
        for k in ("actions", "rewards", "dones"):
            d.create_dataset(k, data=getattr(ep, k))
        for k, v in ep.obs.items():
            d.create_dataset(f"obs/{k}", data=v)
    (back,) = read_dataset(tmp_path)
    assert back.instruction == "pick up the bowl" and back.success


def test_missing_key_is_named(tmp_path):
    path = write_episodes(tmp_path / "a.hdf5", [_episode()])
    with h5py.File(path, "a") as f:
        del f["data/demo_0/obs/agentview_rgb"]
    with pytest.raises(DatasetError, match=r"a.hdf5.*data/demo_0/obs/agentview_rgb"):
        read_episodes(path, ("agentview_rgb", "ee_pos"))  # a camera is required where a reader asks for it
    with h5py.File(path, "a") as f:
        del f["data/demo_0/actions"]
    with pytest.raises(DatasetError, match=r"a.hdf5.*data/demo_0/actions"):
        read_episodes(path)


def test_truncated_file_is_named(tmp_path):
    path = write_episodes(tmp_path / "a.hdf5", [_episode(T=40)])
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="a.hdf5"):
        read_episodes(path)


def test_wrong_schema_is_named(tmp_path):
    with h5py.File(tmp_path / "w.hdf5", "w") as f:
        f.create_dataset("foo", data=np.zeros(3))
    with pytest.raises(DatasetError, match=r"w.hdf5: missing key 'data'"):
        read_episodes(tmp_path / "w.hdf5")
    with pytest.raises(DatasetError, match="shape"):
        Episode(actions=np.zeros(5), obs={}, instruction="x")
    with pytest.raises(DatasetError, match="6-D actions, the action space is ee_delta"):
        write_episodes(tmp_path / "six.hdf5", [Episode(actions=np.zeros((5, 6)), obs={}, instruction="x")])


def test_failed_write_leaves_previous_file(tmp_path):
    path = write_episodes(tmp_path / "a.hdf5", [_episode()])
    before = path.read_bytes()
    bad = _episode()
    bad.obs["agentview_rgb"] = object()  # not an array: h5py fails mid-write, after the first episode
    with pytest.raises(TypeError, match="no native HDF5 equivalent"):
        write_episodes(path, [_episode(), bad])
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["a.hdf5"]


def test_split_is_episode_level_and_stratified():
    eps = [synthetic_episode(np.random.default_rng(i), g, T=5, size=8) for g in ("left", "right") for i in range(5)]
    train, val = split_episodes(eps, 0.2, seed=0)
    assert set(train).isdisjoint(val) and sorted(train + val) == list(range(10))
    assert {eps[i].instruction for i in val} == {"move the square left", "move the square right"}


def test_task_balance_draws_tasks_equally_and_batches_are_a_function_of_the_step():
    tasks, lengths = ["a", "a", "a", "b"], [30, 30, 30, 10]  # task a has 90 frames, b 10
    share_b = lambda w: w[90:].sum()  # noqa: E731
    assert np.allclose(task_balanced_weights(tasks, lengths, 0.0), 1 / 100)
    assert share_b(task_balanced_weights(tasks, lengths, 1.0)) == pytest.approx(0.5)
    assert share_b(task_balanced_weights(tasks, lengths, 0.5)) == pytest.approx(1 / (1 + 3))  # 10**.5 / (.. + 90**.5)
    cdf = np.cumsum(task_balanced_weights(tasks, lengths, 1.0))
    drawn = np.concatenate([weighted_batch_indices(cdf, 32, step, seed=0) for step in range(200)])
    assert drawn.min() >= 0 and drawn.max() < 100
    assert np.mean(drawn >= 90) == pytest.approx(0.5, abs=0.03)
    batch = lambda step: weighted_batch_indices(cdf, 32, step, seed=0)  # noqa: E731
    np.testing.assert_array_equal(batch(7), batch(7))  # a resumed run draws the same batch
    assert not np.array_equal(batch(7), batch(8))
    with pytest.raises(ValueError, match="task balance"):
        task_balanced_weights(tasks, lengths, 1.5)


def test_the_shift_moves_only_the_named_cameras():
    images = np.random.default_rng(0).integers(0, 256, (6, 2, 16, 16, 3), dtype=np.uint8)
    out = augment_shift(images, np.random.default_rng(1), 3, cameras=(0,))
    assert np.array_equal(out[:, 1], images[:, 1])  # the wrist view as it was
    alone = augment_shift(images[:, [0]], np.random.default_rng(1), 3)[:, 0]
    assert np.array_equal(out[:, 0], alone) and not np.array_equal(out[:, 0], images[:, 0])
    assert not np.array_equal(augment_shift(images, np.random.default_rng(1), 3)[:, 1], images[:, 1])


def test_chunk_targets_padding_mask_and_next_obs():
    cfg = ModelConfig(image_size=16, chunk=8, horizon=5)
    ep = _episode(T=10)
    stats = fit_norm_stats([ep], cfg)
    ds = ChunkDataset([prepare_episode(ep, cfg, stats, WordTokenizer.build([ep.instruction]))], cfg, sp_steps=2)
    rng = np.random.default_rng(0)
    s = ds.sample(6, rng)  # t = 6: steps 6..13, only 6..9 exist
    assert s["action_mask"].tolist() == [1, 1, 1, 1, 0, 0, 0, 0]
    np.testing.assert_array_equal(s["actions"][4:], np.repeat(s["actions"][3:4], 4, axis=0))
    assert s["value_mask"].tolist() == [1, 1, 1, 1, 0, 0]
    assert (s["sp_index"] + 1 <= 3).all()  # o_{t+k} must exist: t + k <= 9
    assert s["images"].shape == (2, 16, 16, 3) and s["sp_images"].shape == (2, 2, 16, 16, 3)
    prepared = ds.episodes[0]
    np.testing.assert_array_equal(s["sp_images"], prepared.images[6 + s["sp_index"] + 1])
    np.testing.assert_array_equal(s["sp_proprio"], prepared.proprio[6 + s["sp_index"] + 1])  # the same o_{t+k}
    last = ds.sample(9, rng)
    assert last["sp_mask"].tolist() == [0, 0]


@pytest.mark.parametrize("on_disk", [False, True])
def test_streamed_episodes_share_one_picture_store(tmp_path, on_disk):
    """Episodes prepared one at a time into one store (in memory, or in an unnamed file) equal those prepared
    alone; a stream that no longer matches the lengths read before is refused."""
    cfg = ModelConfig(image_size=16)
    eps = [_episode(T=T, seed=T) for T in (7, 12, 5)]
    stats, text = fit_norm_stats(eps, cfg), WordTokenizer.build([eps[0].instruction])
    store = image_store(24, cfg, tmp_path / "cache" if on_disk else None)
    assert isinstance(store, np.memmap) == on_disk and store.shape == (24, 2, 16, 16, 3)
    if on_disk:
        assert list((tmp_path / "cache").iterdir()) == []  # nothing to delete, even after a crash
    prepared = prepare_episodes(iter(eps), [7, 12, 5], cfg, stats, text, store)
    for ep, p in zip(eps, prepared):
        alone = prepare_episode(ep, cfg, stats, text)
        np.testing.assert_array_equal(p.images, alone.images)
        np.testing.assert_array_equal(p.actions, alone.actions)
        assert np.shares_memory(p.images, store)
    with pytest.raises(DatasetError, match="episode 1 changed"):
        prepare_episodes(iter(eps), [7, 11, 5], cfg, stats, text, store)
    with pytest.raises(DatasetError, match="more than the 2 episodes read before"):
        prepare_episodes(iter(eps), [7, 12], cfg, stats, text, store)
    with pytest.raises(DatasetError, match="2 episodes read where there were 3"):
        prepare_episodes(iter(eps[:2]), [7, 12, 5], cfg, stats, text, store)


def test_action_stats_q99_and_binary_gripper():
    a = np.random.default_rng(0).normal(0, 0.1, size=(1000, 7)).astype(np.float32)
    a[:, 6] = np.where(a[:, 6] > 0, 1.0, -1.0)
    st = ActionStats.fit(a)
    n = st.normalize(a)
    assert n.min() >= -1 and n.max() <= 1
    assert set(np.unique(n[:, 6])) == {-1.0, 1.0}
    inside = (a[:, :6] > st.q01[0]) & (a[:, :6] < st.q99[0])
    np.testing.assert_allclose(st.unnormalize(n)[:, 0][inside[:, 0]], a[:, 0][inside[:, 0]], atol=1e-5)


def test_gae_hand_computed_episode():
    r = np.array([0.0, 0.0, 1.0], np.float32)
    v = np.array([0.5, 0.6, 0.8], np.float32)
    d = np.array([0, 0, 1], np.float32)
    g, lam = 0.9, 0.5
    d2 = 1.0 - 0.8
    d1 = 0.0 + g * 0.8 - 0.6
    d0 = 0.0 + g * 0.6 - 0.5
    a2 = d2
    a1 = d1 + g * lam * a2
    a0 = d0 + g * lam * a1
    adv, ret = gae(r, v, d, g, lam)
    np.testing.assert_allclose(adv, [a0, a1, a2], atol=1e-6)
    np.testing.assert_allclose(ret, [a0 + 0.5, a1 + 0.6, a2 + 0.8], atol=1e-6)


def test_a_damaged_file_reads_or_fails_naming_itself(tmp_path):
    """Bytes overwritten anywhere in a file: reading it either works or raises DatasetError with the path,
    never a bare h5py OSError or KeyError."""
    from pivla.data.episode import DatasetError
    from pivla.data.hdf5 import read_episodes

    good = write_episodes(tmp_path / "good.hdf5", [_episode(), _episode()]).read_bytes()
    rng = np.random.default_rng(0)
    failures = 0
    for i, offset in enumerate(rng.integers(0, len(good) - 64, 150)):
        damaged = bytearray(good)
        damaged[offset:offset + 64] = rng.integers(0, 256, 64, dtype=np.uint8).tobytes()
        path = tmp_path / f"damaged{i}.hdf5"
        path.write_bytes(bytes(damaged))
        try:
            read_episodes(path)
        except DatasetError as e:
            assert str(path) in str(e)
            failures += 1
    assert failures > 0  # some damage is seen (the rest hits bytes no reader checks, e.g. image pixels)


@pytest.mark.parametrize("field", ["actions", "rewards", "ee_pos"])
def test_a_nan_in_a_file_is_named_with_the_file_and_step(tmp_path, field):
    from pivla.data.episode import DatasetError
    from pivla.data.hdf5 import read_episodes

    path = write_episodes(tmp_path / "a.hdf5", [_episode(), _episode()])
    with h5py.File(path, "r+") as f:
        g = f["data/demo_1"]
        dset = g["obs"][field] if field == "ee_pos" else g[field]
        values = dset[()]
        values[2] = np.nan
        dset[...] = values
    with pytest.raises(DatasetError, match=rf"a.hdf5: data/demo_1: {field} holds NaN or inf \(first at step 2\)"):
        read_episodes(path)
