"""The benchmark scripts keep working: each runs once in its tiny setting.

The numbers of a tiny run mean nothing (a tiny model, a few steps, a shared machine); these tests
check that every script runs end to end and writes a complete table with the environment.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from bench_pages import table_rows
from conftest import REPO
from mfg_lightning.scene import boxes, camera, raycast

BENCH = REPO / "bench"

pytestmark = pytest.mark.slow


def _run_bench(script: str, out: Path, *args: str) -> str:
    """Run ``bench/<script> --tiny`` on one thread; return the Markdown file it wrote."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", MFG_CACHE_DIR=str(out))
    command = [sys.executable, str(BENCH / script), "--tiny", "--out", str(out), *args]
    proc = subprocess.run(command, cwd=out, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"{script} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
    path = out / f"{Path(script).stem}.md"
    text = path.read_text()
    # Printed as written, with the command, the cores and the versions.
    tables = [line for line in text.splitlines() if line.startswith("| ")]
    assert tables and tables[0] in proc.stdout
    for needle in ("## Environment", f"bench/{script}", "cores (usable / total)", "| torch |"):
        assert needle in text, needle
    return text


def _number(cell: str) -> float:
    return float(cell.replace(" %", "").replace("+", ""))


def test_accuracy_benchmark(tmp_path: Path, shared_poses: Path) -> None:
    text = _run_bench("accuracy.py", tmp_path, "--poses-dir", str(shared_poses), "--threads", "1")
    expected = (
        "MFG (all units)",
        "MFG top-k 5 %",
        "MFG top-k 2 %",
        "essential matrix + RANSAC (OpenCV)",
        "continuous least squares (§3, Bruss–Horn)",
        "oracle: exact fields → recover_motion",
    )
    # the same methods on the exact flow and on DIS flow of rendered worlds
    for heading in ("## Exact flow", "## DIS flow of rendered worlds"):
        rows = {r[0]: r for r in table_rows(text, heading)}
        for name in expected:
            assert name in rows, (heading, name)
            ate09, ate10 = (re.match(r"([\d.e-]+) ± ([\d.e-]+)", rows[name][i]) for i in (1, 2))
            assert ate09 and ate10, rows[name]
            assert all(math.isfinite(float(x)) for x in (*ate09.groups(), *ate10.groups()))
        # The oracle is the floor: the closed form itself, float32 rounding only.
        assert float(rows["oracle: exact fields → recover_motion"][1].split(" ± ")[0]) < 1e-5
        # The paper's numbers are quoted beside MFG, labelled as on real KITTI images.
        assert rows["MFG (all units)"][6] == "0.012 ± 0.006"
    assert "real KITTI images" in text
    # the flow's own table: EPE and Fl per region on the noc and all pixels, and the cost
    quality = (tmp_path / "flow_quality.md").read_text()
    splits = {(r[0], r[1]): r for r in table_rows(quality, "## Quality by region")}
    assert set(splits) == {(s, p) for s in ("train", "val", "test") for p in ("noc", "all")}
    assert splits["test", "all"][2:4] == ["medium", "64×128"]
    for pixels in ("noc", "all"):
        assert math.isfinite(_number(splits["test", pixels][-3]))  # EPE of the whole image
    assert _number(splits["test", "noc"][4]) <= _number(splits["test", "all"][4])  # per pair
    parts = {r[0]: r for r in table_rows(quality, "## Cost of rendering")}
    assert set(parts) == {"train+val", "test"}
    assert "faster** (target ≥ 50×)" in quality


def test_throughput_benchmark(tmp_path: Path) -> None:
    text = _run_bench("throughput.py", tmp_path, "--threads", "1")
    peaks = {r[0]: r[1] for r in table_rows(text, "## GEMM peak and the model's FLOPs")}
    assert _number(peaks["256² matmul, float32 (GFLOP/s)"]) > 0
    assert _number(peaks["256² matmul, bfloat16 (GFLOP/s)"]) > 0
    assert _number(peaks["network forward (GFLOP / sample)"]) > 0
    assert _number(peaks["network backward (GFLOP / sample)"]) > 0
    training = table_rows(text, "## Training: Lightning Trainer against a bare PyTorch loop")
    # float32 and bf16-mixed side by side at every batch size, through Lightning and bare.
    assert {(r[0], r[1]) for r in training} == {
        (b, p) for b in ("1", "2", "4") for p in ("float32", "bf16-mixed")
    }
    for row in training:
        # Rates, "ratio (min–max)", the step-paired "ratio (q1–q3)", ms/step; then the
        # difference in ms/step (either sign).
        assert all(_number(c.split()[0]) > 0 for c in row[2:7]), row
        q1, q3 = (float(x) for x in row[5].split("(")[1].rstrip(")").split("–"))
        assert q1 <= float(row[5].split()[0]) <= q3, row
        assert math.isfinite(float(row[7])), row
        # Each rate as a fraction of its own dtype's GEMM peak.
        assert all(_number(c) > 0 for c in row[8:10]), row
    ratios = table_rows(text, "## bf16-mixed against float32")
    assert [r[0] for r in ratios] == ["1", "2", "4"]
    assert all(_number(r[1].split()[0]) > 0 and _number(r[2].split()[0]) > 0 for r in ratios)
    inference = table_rows(text, "## Inference")
    assert [r[0] for r in inference] == ["1", "2", "4"]
    assert all(_number(r[1]) > 0 and _number(r[2]) > 0 for r in inference)
    # Loader-only rates: the generator in process and in a worker, cached DIS flow.
    loaders = table_rows(text, "## The data: loader-only rates")
    assert len(loaders) == 4 and all(r[1].isdigit() for r in loaders), loaders
    assert "one DataLoader worker" in loaders[2][0] and "DIS" in loaders[3][0]
    on_data = table_rows(text, "Training on the real loader:")
    assert [r[0] for r in on_data] == ["float32", "bf16-mixed"]
    assert _number(table_rows(text, "## Peak resident memory")[0][1]) > 50
    faults = table_rows(text, "## Host memory kept")
    assert [(r[0], r[1]) for r in faults] == [
        ("float32", "default"), ("float32", "kept"), ("bf16-mixed", "default"),
        ("bf16-mixed", "kept"),
    ]  # fmt: skip
    assert all(_number(r[4]) > 0 for r in faults)
    assert "aten::" in text  # the profiles
    assert "## Profile of the bare training step, batch 4, bf16-mixed" in text
    kernels = table_rows(text, "## Per-layer kernels")
    assert kernels[0][0].startswith("`encoder.0 Conv2d") and "decoder_omega" in kernels[-1][0]
    # each convolution with the implementation each precision computes it with
    impls = {"native", "im2col", "channels_last"}
    assert all(set(r[1].split(" / ")) <= impls for r in kernels[:-2]), kernels
    assert kernels[-1][1] == "- / -"
    candidates = {r[1] for r in table_rows(text, "## Candidate speed-ups")}
    assert {
        "float32 + channels-last",
        "bf16 + channels-last",
        "bf16 + first conv in float32",
        "bf16 + first conv's input padded to 8 channels",
    } <= candidates
    # The sample cache, a section of its own: every loader's epochs 1 and 2, alone and training.
    cache = {r[0]: r for r in table_rows(text, "## The sample cache: samples computed once")}
    assert len(cache) == 6 and "cache, `prefetch=worker`" in cache
    for row in (r for r in cache.values() if r[1] != "-"):
        assert all(_number(c) > 0 for c in (*row[1:3], row[4], row[6])), row  # samples/s
        assert _number(row[8].split()[0]) > 0, row  # the ratio to the batches held in memory
        assert math.isfinite(_number(row[5])) and math.isfinite(_number(row[7])), row
    held = cache["the same batches, collated once, in memory"]
    assert _number(held[4]) > 0 and _number(held[6]) > 0
    # Each row measures what it says: epoch 2 generated without the cache, read from memory
    # with it, from the files of an earlier run with the memory tier off.
    served = {label.split(":")[0]: r[3] for label, r in cache.items()}
    assert served["no cache"] == "computed (no cache)"
    assert served["cache, `prefetch=none`"] == served["cache, `prefetch=thread` (the default)"]
    n_train = re.search(r"\((\d+) training samples per epoch\)", text)
    assert n_train and served["cache, `prefetch=none`"] == f"memory {n_train.group(1)}"
    assert served["cache on disk only, filled by an earlier run (`memory_mb=0`)"] == (
        f"disk {n_train.group(1)}"
    )
    # 7. The convolutions' implementations, a marked section: the CPU and its features named,
    # every layer's three times and the choice, then the step with the choice against native.
    section = text.split("<!-- conv-impl:start -->", 1)[1].split("<!-- conv-impl:end -->")[0]
    assert "AVX2" in section and "AVX512-BF16" in section and "AMX" in section
    layers = table_rows(section, "## Convolution implementations per layer")
    assert [r[0].split()[0] for r in layers[:8]] == [
        f"`encoder.{i}`" for i in (0, 2, 4, 6, 8, 10, 12, 14)
    ]
    assert layers[8][0] == "all convolutions" and layers[0][2] == "float32"
    for row in layers:
        assert all(_number(c) > 0 for c in row[3:6]) and _number(row[7]) > 0, row
        assert row[6] in ("native", "im2col", "channels_last", "per layer"), row
    step = table_rows(section, "Training step with the chosen implementations")
    assert step[0][:2] == ["4", "float32"] and _number(step[0][3]) > 0


def test_quick_start_benchmark(tmp_path: Path) -> None:
    """The quick start without and with the sample cache, in a section named after the
    instruction set torch's kernels use; the cache changes no test metric."""
    import torch

    text = _run_bench("throughput.py", tmp_path, "--threads", "1", "--quick-start")
    capability = torch.backends.cpu.get_cpu_capability()
    rows = table_rows(text, f"## The quick start at {capability}")
    assert [r[0].split(" (")[0].split(",")[0] for r in rows] == [
        "without the cache", "the defaults", "the defaults", "device-resident", "device-resident"
    ]  # fmt: skip
    assert all(_number(r[1]) > 0 and _number(r[3]) > 0 for r in rows)
    assert rows[0][2] == "1.00" and len({(r[5], r[6]) for r in rows}) == 1, rows
    # the precision and kernels read from the committed table, the work against the machine's
    # limit, and where a profiled run of the defaults spent its time (Lightning's SimpleProfiler)
    assert "kernels from this CPU kind's row of conf/cpu_defaults.yaml" in text
    limit = next(line for line in text.splitlines() if "the limit: all of it at the peak" in line)
    assert _number(limit.split("|")[2]) > 0
    assert "`fit: run_training_batch`" in text


def test_flow_estimators_benchmark(tmp_path: Path, shared_poses: Path) -> None:
    """Three estimators on the tiny pair set of both sets of worlds (scene seed 0's and the
    study's test worlds), the learned one among them: a row each per set of pixels (noc, all),
    by region and by offset; the stages are cached and a rerun reads them."""
    args = ("--poses-dir", str(shared_poses), "--work", str(tmp_path / "work"),
            "--estimators", "dis_medium", "farneback", "learned")  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS="1", MFG_CACHE_DIR=str(tmp_path))
    command = [sys.executable, str(BENCH / "flow_estimators.py"), "--tiny", "--out",
               str(tmp_path), *args]  # fmt: skip
    proc = subprocess.run(command, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-5000:]
    text = (tmp_path / "flow_quality.md").read_text()  # a section of flow_quality.md
    assert "### Environment of this section" in text and "opencv" in text
    labels = ["DIS medium", "Farnebäck", "learned (PWC-Net design)"]
    for heading, seed in (("### Scene seed 0's worlds", 0), ("### The study's worlds", 7919)):
        rows = table_rows(text, heading)
        assert [r[0] for r in rows[:6:2]] == labels, heading
        assert [r[1] for r in rows[:6]] == ["noc", "all"] * 3
        assert all(_number(r[2]) > 0 and 0 < _number(r[-2]) < 100 for r in rows[:6])
        assert f"world seed {seed})" in text.split(heading, 1)[1]
    assert sorted(p.name for p in (tmp_path / "work").iterdir()) == [
        "dis_medium_study_tiny.json", "dis_medium_tiny.json", "farneback_study_tiny.json",
        "farneback_tiny.json", "learned_study_tiny.json", "learned_tiny.json",
    ]  # fmt: skip


def test_scaleout_benchmark(tmp_path: Path) -> None:
    text = _run_bench("scaleout.py", tmp_path, "--threads", "1")
    rates = table_rows(text, "## Training throughput")
    assert [r[0] for r in rates] == ["2"]  # the tiny run: DDP only
    reduction = table_rows(text, "## Metric reduction")
    assert reduction[0][0] == "`test/trans_err`"
    worst = re.search(r"largest relative difference is ([\d.e+-]+)", text)
    assert worst and float(worst.group(1)) <= 1e-5


def test_flow_cache_benchmark(tmp_path: Path) -> None:
    text = _run_bench("flow_cache.py", tmp_path, "--threads", "1")
    rows = {r[0]: r for r in table_rows(text, "frame pairs of a")}
    assert len(rows) == 4
    cold = rows["epoch 1 (cold cache: decode, DIS, write)"]
    warm = rows["epoch 2 (same dataset, cache hits)"]
    assert float(cold[1]) > 0 and float(warm[1]) > 0
    assert float(rows["a later run (new dataset, same cache)"][3].rstrip("×")) > 0


def test_run_all_runs_every_script_and_fails_loudly(tmp_path: Path) -> None:
    import importlib.util

    spec = importlib.util.spec_from_file_location("run_all", BENCH / "run_all.py")
    assert spec and spec.loader
    run_all = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(run_all)
    assert set(run_all.SCRIPTS) | set(run_all.GPU_SCRIPTS) == {
        p.name for p in BENCH.glob("*.py")
    } - {
        "run_all.py",
        "_common.py",
        "install_gpu.py",  # the GPU set-up that `make gpu-check` runs first, not a benchmark
        "install_opencv.py",  # the OpenCV step of `make install`, not a benchmark
    }
    # An unknown argument makes every script fail: run_all reports it with a non-zero status.
    assert run_all.main(["--no-such-option"]) == 1


def test_grid_ray_cast_equals_the_general_ray_cast() -> None:
    """The generator's fast path (``ray_cast_grid``, timed by bench/throughput.py) renders
    exactly what the general ray caster gives for the same rays."""
    from mfg_lightning.core import geometry

    K = camera.kitti_like_intrinsics(40, 96)
    xy = geometry.normalized_grid(K[None], 40, 96)[0]
    rays = torch.stack([xy[0].flatten(), xy[1].flatten(), torch.ones(40 * 96, dtype=xy.dtype)], -1)
    rng = np.random.default_rng(0)
    hits = set()
    for _ in range(30):
        corners = torch.from_numpy(boxes.sample_boxes(rng, boxes.SceneConfig())[0])
        depth, hit = raycast.ray_cast(rays, corners)
        depth_g, hit_g = raycast.ray_cast_grid(xy[0, 0], xy[1, :, 0], corners)
        assert torch.equal(depth_g.flatten(), depth)
        assert torch.equal(hit_g.flatten(), hit)
        hits |= set(hit.unique().tolist())
    # Sky, ground and boxes were all hit: every branch was compared.
    assert {-2, -1} <= hits and max(hits) >= 0
    # No boxes at all: sky and ground only.
    depth_0, hit_0 = raycast.ray_cast_grid(xy[0, 0], xy[1, :, 0], torch.zeros(0, 2, 3))
    assert torch.equal(hit_0.flatten(), raycast.ray_cast(rays, torch.zeros(0, 2, 3))[1])
    assert torch.equal(depth_0.flatten(), raycast.ray_cast(rays, torch.zeros(0, 2, 3))[0])


def test_committed_command_lines_name_no_absolute_path(monkeypatch, tmp_path: Path) -> None:
    """A result's command line: paths in the repository relative to it, ``../shared`` beside it,
    the cache as ``<cache>``, anything else as ``<path>``."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_common", BENCH / "_common.py")
    assert spec and spec.loader
    common = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(common)
    monkeypatch.setenv("MFG_CACHE_DIR", str(tmp_path / "cache"))
    argv = [str(BENCH / "accuracy.py"), "--poses-dir", str(REPO.parent / "shared" / "poses"),
            "--work", str(tmp_path / "cache" / "w"), "--out", "/elsewhere/x", "--tiny"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    assert common.command_line() == (
        "python bench/accuracy.py --poses-dir ../shared/poses --work '<cache>/w' "
        "--out '<path>' --tiny"
    )
