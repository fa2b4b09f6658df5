"""Is the KITTI flow cache worth it? The first epoch against the second over the same frames.

``dataset=kitti`` computes optical flow with OpenCV's DIS the first time a frame pair is read and
caches it on disk (``<cache_dir>/kitti_flow/<key>/...``); every later epoch and every later run
with the same parameters reads the cache. This script writes a KITTI odometry tree at the real
resolution (1241 × 376, textured frames moving by a known shift, as ``tests/fake_datasets.py``
writes them for the loader tests) into a temporary directory and times, for the same frames:

1. epoch 1: every sample read once, cache cold (decode both PNGs, DIS, resize, atomic write);
2. epoch 2: the same dataset object again (cache hits);
3. a later run: a new dataset object on the same cache directory;
4. ``prepare_data``'s precompute (the path a training run takes: pairs in frame order, each
   image decoded once) into a second, empty cache, for comparison with epoch 1.

``python bench/flow_cache.py`` (about a minute on 2 CPU cores); ``--tiny`` for a smoke run.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO, Report, add_common_arguments, markdown_table

#: The frames a KITTI odometry colour camera delivers (image_2), width × height.
KITTI_WIDTH, KITTI_HEIGHT = 1241, 376


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=41, help="frames of the sequence (pairs + 1)")
    p.add_argument("--preset", default="medium", help="DIS preset (the dataset's default)")
    add_common_arguments(p, "OpenCV / torch threads", "seconds-long smoke run (small frames)")
    return p.parse_args(argv)


def epoch_seconds(dataset) -> list[float]:
    """Read every sample of ``dataset`` once, in order; the seconds each read took."""
    times = []
    for i in range(len(dataset)):
        start = time.perf_counter()
        dataset[i]
        times.append(time.perf_counter() - start)
    return times


def main(argv: list[str] | None = None) -> Path:
    args = parse_args(argv)
    import cv2
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
        cv2.setNumThreads(args.threads)
    # The tree writer of the loader tests: the published layout, real PNG encoding.
    sys.path.insert(0, str(REPO / "tests"))
    from fake_datasets import make_kitti
    from mfg_lightning.data.kitti import KittiOdometryDataset

    width, height = (200, 64) if args.tiny else (KITTI_WIDTH, KITTI_HEIGHT)
    frames = 5 if args.tiny else args.frames
    report = Report(
        "flow_cache", "KITTI flow cache: first epoch against later epochs", out_dir=args.out
    )
    with tempfile.TemporaryDirectory(prefix="mfg-bench-flow-cache-") as tmp_name:
        tmp = Path(tmp_name)
        fake = make_kitti(
            tmp / "kitti", sequences=("09",), n_frames=frames, height=height, width=width
        )

        def dataset(cache: Path) -> KittiOdometryDataset:
            return KittiOdometryDataset(
                fake.root,
                ["09"],
                height=48,
                width=128,
                cache_dir=cache,
                flow={"source": "dis", "preset": args.preset},
            )

        ds = dataset(tmp / "cache")
        cold = epoch_seconds(ds)
        warm = epoch_seconds(ds)
        later = epoch_seconds(dataset(tmp / "cache"))
        pre = dataset(tmp / "cache-precompute")
        start = time.perf_counter()
        pre.precompute_flow(progress=False)
        precompute = time.perf_counter() - start
        cache_bytes = sum(p.stat().st_size for p in (tmp / "cache").rglob("*") if p.is_file())

    n = len(cold)
    rows = []
    for name, times in (
        ("epoch 1 (cold cache: decode, DIS, write)", cold),
        ("epoch 2 (same dataset, cache hits)", warm),
        ("a later run (new dataset, same cache)", later),
    ):
        total = sum(times)
        rows.append(
            (
                name,
                f"{total:.3f}",
                f"{1e3 * statistics.median(times):.2f}",
                f"{sum(cold) / total:.0f}×" if times is not cold else "1×",
            )
        )
    rows.append(
        (
            "`prepare_data` precompute (cold, each image decoded once)",
            f"{precompute:.3f}",
            f"{1e3 * precompute / n:.2f} (mean)",
            f"{sum(cold) / precompute:.1f}×",
        )
    )
    report.add(
        f"{n} frame pairs of a {width} × {height} sequence (PNG, 3 channels), DIS preset "
        f"`{args.preset}` at the native size, flow resized to the model's 48 × 128; "
        f"`num_workers=0`, one process.\n\n"
        + markdown_table(["pass", "seconds", "ms / sample (median)", "× faster than epoch 1"], rows)
        + f"\nThe cache holds {cache_bytes / 1e3:.0f} kB for these pairs (flow and the "
        "downsized RGB frame as `.npy`), "
        f"{cache_bytes / n / 1e3:.1f} kB per pair. A cached sample still decodes nothing but "
        "two small `.npy` files; the pose and intrinsics are read once per dataset."
    )
    return report.write()


if __name__ == "__main__":
    main()
