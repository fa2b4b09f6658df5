"""``flow=dis`` on the synthetic dataset: rendered worlds, DIS, the cache, the flow quality."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from conftest import run_module
from mfg_lightning.data.rendered import RenderedDrivingDataset
from mfg_lightning.data.rendered_preparation import plan_chunks, prepare_pairs
from mfg_lightning.data.sample import check_sample
from mfg_lightning.data.synthetic import SyntheticDataModule
from mfg_lightning.flow.estimators import (
    ESTIMATORS,
    DISFlowEstimator,
    EstimatedFlow,
    parse_flow,
)
from mfg_lightning.metrics.flow_quality import QUALITY_REGIONS, QUALITY_SETS, flow_quality
from mfg_lightning.scene import render

H, W = 32, 64  # model input
RH, RW = 64, 128  # render size
# the render size of the tiny end-to-end trainings
TINY_FLOW = ["flow=dis", f"flow.height={RH}", f"flow.width={RW}"]


def _dm(cache: Path, estimator: DISFlowEstimator | None = None, **kw) -> SyntheticDataModule:
    flow = EstimatedFlow(estimator or DISFlowEstimator("medium"), RH, RW)
    base = dict(
        height=H, width=W, train_sequences=1, test_sequences=1, sequence_length=8,
        val_fraction=0.3, flow=flow, cache_dir=str(cache),
    )  # fmt: skip
    base.update(kw)
    return SyntheticDataModule(**base)


class _Counting(DISFlowEstimator):
    """DIS that counts its calls (class-wide: prepare_data builds its own datasets)."""

    calls = 0

    def __call__(self, gray0: np.ndarray, gray1: np.ndarray) -> np.ndarray:
        type(self).calls += 1
        return super().__call__(gray0, gray1)


class _Holes(DISFlowEstimator):
    """DIS with a non-finite 4 × 4 block in every estimate."""

    def __call__(self, gray0: np.ndarray, gray1: np.ndarray) -> np.ndarray:
        flow = super().__call__(gray0, gray1).copy()
        flow[8:12, 8:12] = np.nan
        return flow


def _files(root: Path) -> dict[Path, int]:
    return {p: p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}


@pytest.fixture
def count_renders(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    calls: list[int] = []
    original = render.render_frame

    def counting(world, frame, *args, **kwargs):
        calls.append(frame)
        return original(world, frame, *args, **kwargs)

    monkeypatch.setattr(render, "render_frame", counting)
    _Counting.calls = 0
    return calls


def test_prepare_renders_every_frame_once_and_a_second_run_nothing(
    tmp_path: Path, count_renders: list[int]
) -> None:
    cache = tmp_path / "cache"
    dm = _dm(cache, _Counting("medium"))
    dm.prepare_data()
    # train + val pairs of the 8-frame trajectory in one pass, the test trajectory in another:
    # each frame rendered once although it is the target of one pair and the source of the next
    assert sorted(count_renders) == sorted([*range(8), *range(8)])
    assert _Counting.calls == 7 + 7
    assert len(dm.dataset("train")) + len(dm.dataset("val")) == 7
    before = _files(cache)
    assert len([p for p in before if p.suffix == ".npz"]) == 14
    assert len([p for p in before if p.name.startswith("picture-")]) == 2  # one per trajectory
    # a second run on the same cache: nothing rendered, nothing estimated, nothing written
    count_renders.clear()
    again = _dm(cache, _Counting("medium"))
    again.prepare_data()
    again.setup("fit")
    again.setup("test")
    samples = [again.dataset(s)[i] for s in ("train", "val", "test") for i in range(2)]
    assert count_renders == [] and _Counting.calls == 14
    assert _files(cache) == before
    for s in samples:
        check_sample(s, H, W)
    # a setting that changes the flow gets its own cache entry
    other = _dm(cache, DISFlowEstimator("fast")).dataset("test")
    assert other.cache.root != again.dataset("test").cache.root


def _cached_arrays(root: Path) -> dict[str, dict[str, np.ndarray]]:
    """Every cached pair under ``root`` (by path relative to it): its arrays."""
    out = {}
    for path in sorted(root.rglob("*.npz")):
        with np.load(path) as archive:
            out[str(path.relative_to(root))] = {k: archive[k] for k in archive.files}
    return out


def test_chunks_cover_every_pair_once_in_runs_of_whole_source_frames(tmp_path: Path) -> None:
    """The plan alone (nothing rendered): contiguous runs of one sequence each, every pair of
    a source frame in one run, in dataset, sequence and frame order, and a sequence of two
    cut for more processes although a whole-sequence split would give them nothing."""
    dm = _dm(tmp_path, train_sequences=2, test_sequences=2, sequence_length=40, offsets=[-1, 1])
    datasets = [dm.build_dataset("train+val"), dm.build_dataset("test")]
    todo = [list(range(len(ds))) for ds in datasets]
    chunks = plan_chunks(datasets, todo, processes=8, min_pairs=5)
    assert len(chunks) > 4  # 4 sequences, more chunks: every core gets some
    covered = sorted((d, i) for d, ix in chunks for i in ix)
    assert covered == [(d, i) for d, ix in enumerate(todo) for i in ix]
    order = []
    for d, ix in chunks:
        keys = [datasets[d].samples[i] for i in ix]
        assert len({seq for seq, _, _ in keys}) == 1  # one sequence per chunk
        sources = [src for _, src, _ in keys]
        assert sources == sorted(sources) and sources[-1] - sources[0] == len(set(sources)) - 1
        assert len(ix) >= 5
        order.append((d, keys[0][0], sources[0]))
    assert order == sorted(order)
    # no source frame's pairs in two chunks
    owners: dict[tuple[int, str, int], int] = {}
    for c, (d, ix) in enumerate(chunks):
        for i in ix:
            seq, src, _ = datasets[d].samples[i]
            assert owners.setdefault((d, seq, src), c) == c
    # one process, or chunks of at least a sequence: one chunk per sequence
    assert len(plan_chunks(datasets, todo, processes=1, min_pairs=1000)) == 4
    # the chunks shrink with more processes, down to min_pairs
    assert len(plan_chunks(datasets, todo, 2, 5)) < len(chunks)


@pytest.mark.slow
def test_chunked_preparation_in_worker_processes_caches_the_same_pairs(tmp_path: Path) -> None:
    """Two processes on chunks of a few frames from both splits cache the same values, the
    same pictures and the same quality as one process with no chunks; each worker builds a
    sequence's world once, and the quality sums come back from the workers (spawned: seconds).
    """
    setting = dict(offsets=[-1, 1], sequence_length=9)
    serial = _dm(tmp_path / "serial", prepare_workers=0, **setting)
    serial.prepare_data()
    chunked = _dm(tmp_path / "chunked", prepare_workers=2, prepare_chunk_pairs=3, **setting)
    datasets = [chunked.build_dataset("train+val"), chunked.build_dataset("test")]
    todo = [ds.missing() for ds in datasets]
    chunks = plan_chunks(datasets, todo, 2, 3)
    prepared = prepare_pairs(datasets, workers=2, min_chunk_pairs=3, progress=False)
    for ds, done, ix in zip(datasets, prepared, todo, strict=True):
        assert done.processes == 2 and done.pairs == len(ds) == len(ix)
        pieces = sum(1 for d, _ in chunks if datasets[d] is ds)
        assert pieces >= 3
        # one world per sequence and worker, not one per chunk
        assert 1 <= done.worlds <= 2 < pieces
        # the frames at the chunks' borders are rendered by both neighbours
        assert 9 < done.frames <= 9 + 2 * (pieces - 1)
        assert set(done.stats) == set(ds.samples)
        for i in (0, len(ds) - 1):  # what the workers returned is what they cached
            np.testing.assert_array_equal(done.stats[ds.samples[i]], ds._pair_stats(i))
    chunked.prepare_data()  # the quality and the pictures: nothing left to render
    a_root = serial.dataset("test").cache.root.parent
    b_root = chunked.dataset("test").cache.root.parent
    a, b = _cached_arrays(a_root), _cached_arrays(b_root)
    assert set(a) == set(b) and len(a) == sum(len(ds) for ds in datasets)
    for name, arrays in a.items():
        assert set(arrays) == set(b[name])
        for key, array in arrays.items():
            np.testing.assert_array_equal(array, b[name][key], err_msg=f"{name}: {key}")
    for kind in ("picture-*.npy", "quality-*.json"):
        files = sorted(p.relative_to(a_root) for p in a_root.rglob(kind))
        assert files and files == sorted(p.relative_to(b_root) for p in b_root.rglob(kind))
        for f in files:
            assert (a_root / f).read_bytes() == (b_root / f).read_bytes(), f
    # the quality from the returned sums alone: no cached file is read for it
    test = chunked.dataset("test")
    known = prepared[1].stats
    for path in test.cache.root.rglob("*.npz"):
        path.unlink()
    assert test.quality(known) == json.loads(chunked.quality_path("test").read_text())
    with pytest.raises(FileNotFoundError, match="not cached"):
        test.quality()


def test_samples_carry_estimated_and_exact_flow_and_the_quality_is_stored(
    tmp_path: Path,
) -> None:
    dm = _dm(tmp_path / "cache")
    dm.prepare_data()
    ds = dm.dataset("test")
    assert isinstance(ds, RenderedDrivingDataset) and ds.image_hw == (RH, RW)
    s = ds[3]
    assert s["sample_id"] == "synthetic/test/test00/000003->000004"
    assert s["flow_valid"].all()  # DIS gives a vector everywhere
    # the estimate follows the exact flow (a driving scene, not noise): most of the image
    # within a pixel of the model input, and the two differ somewhere
    err = (s["flow"] - s["exact_flow"]).norm(dim=0)
    assert err.median() < 1.0 and err.max() > 0.05
    assert s["exact_flow"].abs().max() > 0.5
    # the ground truth sits beside it: depth, object mask and flow at the model input
    assert (s["depth"] > 0).all() and s["object_flow"][:, ~s["object_mask"]].abs().max() == 0
    quality = json.loads(dm.quality_path("test").read_text())
    assert set(quality["regions"]) == set(QUALITY_REGIONS)
    total = quality["regions"]["all"]
    assert total["pixels"] == len(ds) * RH * RW  # every pixel's exact flow is known here
    parts = [quality["regions"][r]["pixels"] for r in QUALITY_REGIONS[:-1]]
    assert sum(parts) == total["pixels"]
    assert 0 < total["epe"] < 5 and 0 <= total["fl"] < 50
    assert quality["nonfinite_pixels"] == 0
    # KITTI's noc: all pixels but the occluded and out-of-frame ones (some, not most)
    noc = quality["regions_noc"]["all"]
    hidden = quality["occluded_pixels"] + quality["out_of_frame_pixels"]
    assert noc["pixels"] + hidden == total["pixels"] and 0 < hidden < 0.5 * total["pixels"]
    assert 0 < noc["epe"] < 5
    # by offset: the pairs and pixels of every offset add up to the split's pooled quality
    by = ds.quality_by_offset()
    offsets = {str(t - s) for _, s, t in ds.samples}
    assert set(by) == offsets
    assert sum(q["pairs"] for q in by.values()) == len(ds)
    assert sum(q["regions"]["all"]["pixels"] for q in by.values()) == total["pixels"]
    pooled = sum(q["regions"]["all"]["epe"] * q["regions"]["all"]["pixels"] for q in by.values())
    assert pooled / total["pixels"] == pytest.approx(total["epe"])


@pytest.mark.parametrize("name", sorted(set(ESTIMATORS) - {"dis"}))
def test_each_estimator_but_dis_follows_the_exact_flow_of_rendered_frames(
    tmp_path: Path, name: str
) -> None:
    flow = parse_flow({"source": name, "height": RH, "width": RW}, default="exact")
    assert isinstance(flow, EstimatedFlow) and flow.estimator.name == name
    assert flow.key() != parse_flow({"source": "dis", "height": RH, "width": RW}, "exact").key()
    ds = _dm(tmp_path / "cache", flow.estimator).dataset("test")
    s = ds[3]
    assert s["flow_valid"].all()
    # a driving scene's flow with DIS's sign, not noise: most pixels within half a pixel, and
    # closer to the exact flow than no flow at all (at this tiny size, measured: median 0.24 to
    # 0.42 px, mean 0.39 to 0.73 of the exact flow's; flow the other way round gives about 2)
    err = (s["flow"] - s["exact_flow"]).norm(dim=0)
    assert err.median() < 0.5, (name, float(err.median()))
    assert err.mean() < 0.8 * s["exact_flow"].norm(dim=0).mean(), name


def test_input_flow_exact_reads_the_cached_exact_flow_of_the_same_pairs(
    tmp_path: Path, count_renders: list[int]
) -> None:
    """``dataset.input_flow=exact``: the model's ``flow`` is the exact flow of the very pairs
    (and cache) the estimate has; nothing is rendered again and the ground truth is unchanged."""
    cache = tmp_path / "cache"
    est = _dm(cache)
    est.prepare_data()
    count_renders.clear()
    exact = _dm(cache, input_flow="exact")
    exact.prepare_data()
    assert count_renders == []  # the same cache entry: both flows are in every pair
    a, b = est.dataset("test"), exact.dataset("test")
    assert a.cache.root == b.cache.root and a.samples == b.samples
    for i in (0, len(a) - 1):
        sa, sb = a[i], b[i]
        assert torch.equal(sb["flow"], sa["exact_flow"]) and sb["flow_valid"].all()
        assert not torch.equal(sb["flow"], sa["flow"])
        for key in ("exact_flow", "depth", "object_mask", "object_flow", "pose"):
            assert torch.equal(sa[key], sb[key])
    # flow=exact: the same samples without the noise and outliers
    plain = dict(height=H, width=W, train_sequences=1, test_sequences=1, sequence_length=8)
    noisy = SyntheticDataModule(**plain).dataset("test")[2]
    clean = SyntheticDataModule(**plain, input_flow="exact").dataset("test")[2]
    assert torch.equal(noisy["pose"], clean["pose"]) and not torch.equal(
        noisy["flow"], clean["flow"]
    )
    with pytest.raises(ValueError, match="input_flow"):
        _dm(cache, input_flow="dis")


def test_flow_quality_is_the_kitti_outlier_definition() -> None:
    exact = np.zeros((2, 4, 2))
    exact[..., 0] = [[1.0, 100.0, 100.0, 10.0], [1.0, 1.0, 1.0, 1.0]]
    est = exact.copy()
    est[0, 0, 0] += 3.5  # > 3 px and > 5 % of 1 px: outlier
    est[0, 1, 0] += 4.0  # > 3 px but < 5 % of 100 px: not an outlier
    est[0, 2, 0] += 6.0  # > 3 px and > 5 % of 100 px: outlier
    est[0, 3, 0] += 2.0  # < 3 px: not an outlier
    region = np.array([[render.REGION_ROAD] * 4, [render.REGION_FAR] * 4], np.uint8)
    valid = np.ones((2, 4), bool)
    valid[1, 3] = False
    q = flow_quality(est, exact, valid, region, noc=valid)[QUALITY_SETS.index("all")]
    road, far, everything = (QUALITY_REGIONS.index(r) for r in ("road", "far", "all"))
    np.testing.assert_allclose(q[road], [3.5 + 4.0 + 6.0 + 2.0, 2, 4])
    np.testing.assert_allclose(q[far], [0.0, 0, 3])
    np.testing.assert_allclose(q[everything], [15.5, 2, 7])


def test_non_finite_estimates_are_masked_and_counted(tmp_path: Path) -> None:
    dm = _dm(tmp_path / "cache", _Holes("ultrafast"), test_sequences=1, sequence_length=6)
    dm.prepare_data()
    s = dm.dataset("test")[0]
    # 16 pixels of 64 × 128 cover one pixel of the 32 × 64 input (and touch its neighbours)
    assert not s["flow_valid"].all() and s["flow_valid"].float().mean() > 0.98
    assert torch.isfinite(s["flow"]).all()
    quality = json.loads(dm.quality_path("test").read_text())
    assert quality["nonfinite_pixels"] == 16 * len(dm.dataset("test"))


def test_render_sizes_and_world_settings_the_scene_cannot_take_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="flow.width=8"):
        _dm(tmp_path, flow={"source": "dis", "height": 64, "width": 8})
    with pytest.raises(ValueError, match="flow.height=5000"):
        _dm(tmp_path, flow={"source": "dis", "height": 5000, "width": 512})
    with pytest.raises(ValueError, match=r"unknown dataset.world setting\(s\) \['lanes'\]"):
        _dm(tmp_path, world={"lanes": 2})
    # a world setting is part of the cache key
    wide = _dm(tmp_path, world={"lanes_per_side": 2}).build_dataset("test")
    assert wide.cache.root != _dm(tmp_path).build_dataset("test").cache.root
    assert not any(tmp_path.joinpath("synthetic_flow").rglob("*.npz"))


def test_crossing_objects_are_rendered_and_keyed_only_where_a_world_has_them(
    tmp_path: Path,
) -> None:
    """A world without crossings keeps its renderer key whatever the crossings' module holds; a
    world with them (given as a range on the command line would be: a list) renders them as
    moving objects of their own instance ids."""
    plain = _dm(tmp_path, test_sequences=1, sequence_length=6).build_dataset("test")
    none = _dm(tmp_path, test_sequences=1, sequence_length=6, world={"crossing_per_100m": 0.0})
    assert none.build_dataset("test").cache_key()["renderer"] == plain.cache_key()["renderer"]
    crossing = {"crossing_per_100m": 60.0, "crossing_speed": [0.5, 1.0]}
    ds = _dm(tmp_path, test_sequences=1, sequence_length=6, world=crossing).build_dataset("test")
    assert ds.cache_key()["renderer"] != plain.cache_key()["renderer"]
    assert ds.cache_key()["world"] == {"crossing_per_100m": 60.0, "crossing_speed": [0.5, 1.0]}
    world = ds.world(ds.samples[0][0])
    first = len(plain.world(plain.samples[0][0]).moving)
    assert world.first == first and len(world.moving) > first
    frame = render.render_frame(world, 2, ds.image_intrinsics, *ds.image_hw)
    seen = set(frame.instance.unique().tolist())
    assert any(i >= first for i in seen), seen  # crossing objects in view


@pytest.mark.slow
def test_training_on_dis_flow_end_to_end_logs_quality_and_pictures(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run_module(
        "mfg_lightning.train", "debug=tiny", *TINY_FLOW, f"hydra.run.dir={run}", cwd=tmp_path
    )
    metrics = json.loads((run / "metrics.json").read_text())["metrics"]
    assert np.isfinite(metrics["test/trans_err"])
    events = EventAccumulator(str(run / "tensorboard"), size_guidance={"images": 0, "scalars": 0})
    events.Reload()
    scalars = set(events.Tags()["scalars"])
    for split in ("train", "val", "test"):
        for region in ("road", "structure", "all"):
            assert f"{split}/flow_epe/{region}" in scalars, (split, region)
            assert f"{split}/flow_fl/{region}" in scalars, (split, region)
    images = set(events.Tags()["images"])
    assert {"train/flow_picture/train00", "test/flow_picture/test00"} <= images
    # one column of six titled panels: the renderer's four, the estimate and its error
    picture = events.Images("train/flow_picture/train00")[0]
    assert picture.width >= RW and picture.height > 3 * picture.width
