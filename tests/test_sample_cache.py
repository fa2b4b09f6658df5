"""Samples computed once (``dataset.sample_cache``) and the first epoch computed ahead
(``dataset.prefetch``): samples read back bit for bit from memory or disk, the key, the memory
budget, corrupt entries recomputed with a warning, and training identical whoever produces the
samples."""

from __future__ import annotations

import logging
import os
import pickle
from pathlib import Path
from typing import Any

import lightning as L
import pytest
import torch
from hydra.utils import instantiate
from torch.utils.data import DataLoader, Dataset

from mfg_lightning.core.atomic import atomic_write_bytes
from mfg_lightning.core.config import compose
from mfg_lightning.data.driving import SyntheticDrivingDataset
from mfg_lightning.data.resumable_loader import ResumableDataLoader
from mfg_lightning.data.sample_cache import SampleCacheSettings, read_entry
from mfg_lightning.data.synthetic import SyntheticDataModule
from mfg_lightning.run.runs import build_model, build_trainer

H, W = 18, 30  # 540 pixels: the bit-packed masks end in a partial byte
OFF = {"memory_mb": 0, "disk": False}  # no cache: every read generates the sample


def _dm(cache_dir: Path | None = None, **kw: Any) -> SyntheticDataModule:
    base: dict[str, Any] = dict(
        height=H, width=W, train_sequences=2, test_sequences=1, sequence_length=10,
        val_fraction=0.3, scene={"moving_objects": 4}, scene_seed=0, cache_dir=cache_dir,
    )  # fmt: skip
    base.update(kw)
    return SyntheticDataModule(**base)


def _train(cache_dir: Path | None = None, **kw: Any) -> SyntheticDrivingDataset:
    ds = _dm(cache_dir, **kw).dataset("train")
    assert isinstance(ds, SyntheticDrivingDataset)
    return ds


def _assert_same(a: dict, b: dict) -> None:
    """The same keys in the same order; every tensor of the same dtype, shape, strides and
    bytes; every other field equal."""
    assert list(a) == list(b)
    for key, value in a.items():
        if isinstance(value, torch.Tensor):
            other = b[key]
            assert (value.dtype, value.shape, value.stride()) == (
                other.dtype,
                other.shape,
                other.stride(),
            ), key
            assert value.numpy().tobytes() == other.numpy().tobytes(), key
        else:
            assert value == b[key], key


@pytest.mark.parametrize(
    "settings",
    [
        {},  # noise and outliers: the flow is C-contiguous
        {"input_flow": "exact"},  # no noise: the generator's flow is channels-last
    ],
)
def test_cached_samples_are_the_generated_ones_bit_for_bit(
    tmp_path: Path, settings: dict[str, Any]
) -> None:
    plain = _train(sample_cache=OFF, **settings)
    assert plain.store is None
    fresh = [plain[i] for i in range(len(plain))]
    assert any(bool(s["object_mask"].any()) for s in fresh)  # object flow to encode
    cached = _train(tmp_path, **settings)
    for _ in range(2):  # computed and kept, then from memory
        for i, want in enumerate(fresh):
            _assert_same(want, cached[i])
    n = len(fresh)
    assert cached.store.counts == {"memory": n, "disk": 0, "computed": n, "prefetched": 0}
    # A later run reads the disk tier (nothing kept in memory here).
    disk = _train(tmp_path, sample_cache={"memory_mb": 0}, **settings)
    for i, want in enumerate(fresh):
        _assert_same(want, disk[i])
    assert disk.store.counts == {"memory": 0, "disk": n, "computed": 0, "prefetched": 0}
    # Read from disk and kept in memory (decoded), then from memory.
    both = _train(tmp_path, **settings)
    for _ in range(2):
        for i, want in enumerate(fresh):
            _assert_same(want, both[i])
    assert both.store.counts == {"memory": n, "disk": n, "computed": 0, "prefetched": 0}
    # Handed-out tensors are copies: changing one changes no later read.
    cached[0]["flow"].add_(1.0)
    _assert_same(fresh[0], cached[0])


def test_the_key_holds_every_setting_that_changes_a_sample(tmp_path: Path) -> None:
    root = _train(tmp_path).store.root
    assert root.parent == tmp_path / "synthetic_samples"
    changed = [
        {"scene_seed": 1},
        {"height": H + 2},
        {"width": W + 2},
        {"flow": {"source": "exact", "noise_std": 0.5}},
        {"flow": {"source": "exact", "outlier_fraction": 0.02}},
        {"input_flow": "exact"},
        {"scene": {"moving_objects": 2}},
    ]
    for kw in changed:
        assert _train(tmp_path, **kw).store.root != root, kw
    # Neither the training order, the batches, the cache's own settings nor the prefetch.
    same = [
        {"seed": 3},
        {"batch_size": 3},
        {"sample_cache": {"memory_mb": 1}},
        {"prefetch": "thread"},
    ]
    for kw in same:
        assert _train(tmp_path, **kw).store.root == root, kw
    key = (root / "meta.json").read_text()
    for field in ('"format"', '"source"', '"torch"', '"numpy"', '"scene"', '"seed"'):
        assert field in key
    # The poses name each sequence's folder: longer trajectories, other poses, other entries.
    ds, longer = _train(tmp_path), _train(tmp_path, sequence_length=12)
    assert ds.entry_name(0).split("/")[0] != longer.entry_name(0).split("/")[0]
    # Validation shares the training entries (same scenes); test has its own (another seed).
    dm = _dm(tmp_path)
    assert dm.dataset("val").store.root == root
    test = dm.dataset("test").store
    assert test.root != root and test.budget is None  # read once a run: not kept in memory


def test_corrupt_entries_are_recomputed_with_a_warning_naming_the_file(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    fresh = _train(sample_cache=OFF)
    filled = _train(tmp_path)
    for i in range(len(filled)):
        filled[i]
    paths = [filled.store.path(filled.entry_name(i)) for i in range(4)]
    data = [p.read_bytes() for p in paths]
    paths[0].write_bytes(data[0][: len(data[0]) // 2])  # truncated
    flipped = bytearray(data[1])
    flipped[len(flipped) // 2] ^= 0x10
    paths[1].write_bytes(bytes(flipped))  # one bit flipped among the arrays
    flipped = bytearray(data[2])
    flipped[20] ^= 0x01
    paths[2].write_bytes(bytes(flipped))  # one bit flipped in the header
    paths[3].write_bytes(b"")  # empty
    disk_only = {"memory_mb": 0}
    reader = _train(tmp_path, sample_cache=disk_only)
    with caplog.at_level(logging.WARNING, logger="mfg_lightning.data.sample_cache"):
        for i in range(len(reader)):
            _assert_same(fresh[i], reader[i])
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 4
    for path, message in zip(paths, warned, strict=True):
        assert str(path) in message and "computing the sample again" in message
    assert "truncated" in warned[0] and "CRC mismatch" in warned[1]
    assert reader.store.counts["computed"] == 4
    # Rewritten: the next run reads every entry without a warning.
    caplog.clear()
    again = _train(tmp_path, sample_cache=disk_only)
    with caplog.at_level(logging.WARNING, logger="mfg_lightning.data.sample_cache"):
        for i in range(len(again)):
            _assert_same(fresh[i], again[i])
    assert not caplog.records and again.store.counts["disk"] == len(again)
    assert read_entry(paths[0], again.store.fields) is not None


def test_entries_are_written_without_an_fsync(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # What a power loss can leave without it (an empty or torn file) is the corrupt entry above:
    # recomputed. Checkpoints and results keep theirs.
    synced: list[int] = []
    monkeypatch.setattr(os, "fsync", synced.append)
    ds = _train(tmp_path, sample_cache={"memory_mb": 0})
    assert len(synced) == 1  # the directory's key file, once
    ds[0], ds[1]
    assert ds.store.path(ds.entry_name(1)).is_file() and len(synced) == 1
    atomic_write_bytes(tmp_path / "result.json", b"{}")
    assert len(synced) == 2


def test_an_unwritable_disk_tier_is_turned_off_with_one_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    ds = _train(tmp_path, sample_cache={"memory_mb": 0})
    blocker = ds.store.path(ds.entry_name(0)).parent
    blocker.parent.mkdir(parents=True, exist_ok=True)
    blocker.write_text("a file where the sequence's folder goes")
    with caplog.at_level(logging.WARNING, logger="mfg_lightning.data.sample_cache"):
        ds[0], ds[1]
    # reading sample 0's entry fails too (a file in its path), then writing it; nothing after
    entry = blocker.parent / ds.entry_name(0)
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 2
    assert messages[0].startswith(f"sample cache entry {entry} is unusable")
    assert messages[1].startswith(f"sample cache: cannot write {entry}")
    assert messages[1].endswith("not caching on disk")
    assert ds.store.root is None
    _assert_same(_train(sample_cache=OFF)[1], ds[1])


def test_the_memory_budget_bounds_what_the_splits_keep(tmp_path: Path) -> None:
    probe = _train(sample_cache={"disk": False})
    sizes = []
    for i in range(4):
        probe[i]
        sizes.append(sum(a.nbytes for a in probe.store.memory[probe.samples[i]].values()))
    megabytes = (sum(sizes[:3]) + sizes[3] // 2) / 2**20  # room for three samples and a half
    dm = _dm(tmp_path, sample_cache={"memory_mb": megabytes})
    train, val = dm.dataset("train"), dm.dataset("val")
    for ds in (train, val):
        for i in range(len(ds)):
            ds[i]
    assert len(train.store.memory) == 3 and not val.store.memory  # first come, first kept
    assert dm._memory.used <= dm._memory.limit
    for i in range(len(train)):
        train[i]
    assert train.store.counts["memory"] == 3 and train.store.counts["disk"] == len(train) - 3
    # Without a disk tier what memory cannot keep is generated again.
    nodisk = _train(sample_cache={"memory_mb": megabytes, "disk": False})
    for _ in range(2):
        for i in range(len(nodisk)):
            nodisk[i]
    assert nodisk.store.counts["computed"] == 2 * len(nodisk) - 3


class _Share(Dataset):
    """Sample ``i`` of a dataset, and the memory budget of the process that read it."""

    def __init__(self, ds: SyntheticDrivingDataset) -> None:
        self.ds = ds

    def __len__(self) -> int:
        return len(self.ds)

    def __getitem__(self, i: int) -> int:
        self.ds[i]
        return self.ds.store.budget.share


def test_each_loader_worker_keeps_its_share_of_the_budget() -> None:
    ds = _train(sample_cache={"memory_mb": 2, "disk": False})
    loader = DataLoader(_Share(ds), batch_size=None, num_workers=2)
    assert set(loader) == {2**20}  # 2 MB between 2 workers
    assert ds.store.budget.share == 2 * 2**20 and not ds.store.memory  # the parent keeps its own


def test_a_pickled_dataset_starts_with_an_empty_memory(tmp_path: Path) -> None:
    ds = _train(tmp_path)
    want = ds[2]
    copy = pickle.loads(pickle.dumps(ds))  # what a spawned worker gets
    assert not copy.store.memory
    _assert_same(want, copy[2])
    assert copy.store.counts["disk"] == 1


def test_the_prefetch_thread_fills_the_first_epoch_in_the_loader_order(tmp_path: Path) -> None:
    fresh = _train(sample_cache=OFF)
    dm = _dm(tmp_path, prefetch="thread", batch_size=3)
    loader = dm.train_dataloader()
    store = dm.dataset("train").store
    order: list[list[int]] = []
    follow = loader.order.on_order
    loader.order.on_order = lambda indices: (order.append(indices), follow(indices))
    loader.order.set_epoch(0)
    for batch in loader:
        for k, i in enumerate(order[0][: len(batch["sample_id"])]):
            assert batch["sample_id"][k] == fresh[i]["sample_id"]
            assert torch.equal(batch["flow"][k], fresh[i]["flow"])
        order[0] = order[0][len(batch["sample_id"]) :]
    assert store.counts["prefetched"] > 0
    assert store.counts["computed"] + store.counts["disk"] == len(fresh) == len(store.memory)
    # The next epoch reads memory only.
    loader.order.set_epoch(1)
    list(loader)
    assert store.counts["computed"] == len(fresh) - store.counts["disk"]
    dm.teardown("fit")
    assert not dm._prefetchers
    # A pass resumed mid-epoch gives the thread the indices left, in order.
    resumed = ResumableDataLoader(torch.arange(10), seed=0, batch_size=3)
    got: list[list[int]] = []
    resumed.order.on_order = got.append
    resumed.load_state_dict({"epoch": 1, "batches": 2, "samples": 10})
    resumed.order.set_epoch(1)
    assert [i for b in resumed for i in b.tolist()] == got[0]
    assert got[0] == resumed.order.permutation(1)[6:].tolist()


def _train_weights(tmp_path: Path, *overrides: str) -> dict[str, torch.Tensor]:
    """Weights after two epochs of a real training of a tiny model on a tiny set."""
    cfg = compose(
        "train",
        ["dataset.height=32", "dataset.width=64", "model.net.hidden_units=64",
         "model.net.channels=[8,8,16,16,32]", "dataset.batch_size=4", "dataset.train_sequences=2",
         "dataset.sequence_length=9", "dataset.val_fraction=0.2", "trainer.max_epochs=2",
         "trainer.limit_val_batches=0", "logger=none", "callbacks=none", "test=false",
         "model.image_log_every_n_steps=0",
         f"paths.output_dir={tmp_path}", f"paths.cache_dir={tmp_path / 'cache'}", *overrides],
    )  # fmt: skip
    L.seed_everything(cfg.seed, workers=True)
    dm = instantiate(cfg.dataset)
    model = build_model(cfg)
    trainer = build_trainer(cfg, [], [])
    trainer.fit(model, datamodule=dm)
    assert trainer.current_epoch == 2
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


@pytest.mark.slow
def test_training_is_bit_identical_whoever_produces_the_samples(tmp_path: Path) -> None:
    """Two epochs (the first computed, the second read back) without any cache and with the
    cache under each prefetch: the same weights, bit for bit."""
    runs = {
        "no cache": ["dataset.sample_cache.memory_mb=0", "dataset.sample_cache.disk=false",
                     "dataset.prefetch=none"],
        "cache, prefetch none": ["dataset.prefetch=none"],
        "cache, prefetch thread": ["dataset.prefetch=thread"],
        "cache, prefetch worker": ["dataset.prefetch=worker"],
    }  # fmt: skip
    weights = {name: _train_weights(tmp_path / str(i), *ov) for i, (name, ov) in
               enumerate(runs.items())}  # fmt: skip
    want = weights.pop("no cache")
    for name, got in weights.items():
        for key, value in want.items():
            assert torch.equal(value, got[key]), (name, key)
    # Each cached run wrote its training samples to its own disk tier (the worker's too).
    for i in (1, 2, 3):
        assert len(list((tmp_path / str(i) / "cache" / "synthetic_samples").rglob("*.sample")))


def test_the_config_defaults_and_bad_settings(tmp_path: Path) -> None:
    cfg = compose("train", [f"paths.cache_dir={tmp_path}"])
    assert cfg.dataset.prefetch == "thread"
    assert SampleCacheSettings.parse(cfg.dataset.sample_cache) == SampleCacheSettings(1024, True)
    dm = instantiate(cfg.dataset)
    assert dm.prefetch == "thread" and dm._memory.limit == 1024 * 2**20
    assert dm.build_dataset("val").store.root.parent == tmp_path / "synthetic_samples"
    for kw, key in [
        ({"prefetch": "fast"}, "dataset.prefetch"),
        ({"sample_cache": {"memory_mb": -1}}, "dataset.sample_cache.memory_mb"),
        ({"sample_cache": {"disk": "yes"}}, "dataset.sample_cache.disk"),
        ({"sample_cache": {"memroy_mb": 1}}, "dataset.sample_cache setting"),
    ]:
        with pytest.raises(ValueError, match=key):
            _dm(**kw)


def test_rendered_pairs_are_kept_in_memory_after_their_first_read(tmp_path: Path) -> None:
    """``flow=dis``: a pair read once comes from memory afterwards (its file is not read
    again), equal to a fresh read of the flow cache."""
    flow = {"source": "dis", "height": 64, "width": 128}
    kw = dict(height=32, width=64, sequence_length=6, flow=flow, train_sequences=1)
    dm = _dm(tmp_path, **kw)
    dm.prepare_data()
    ds = dm.dataset("train")
    first = ds[1]
    ds.pair_path(1).unlink()  # a second read from disk would have to render it again
    rendered = ds.rendered_frames
    _assert_same(first, ds[1])
    assert ds.rendered_frames == rendered and ds.memory.counts["memory"] == 1
    assert not _dm(tmp_path, **kw).dataset("test").memory  # test pairs: not kept
