"""Which optical-flow estimator gives the rendered worlds' best flow, and at what cost?

Every estimator the framework has (``flow=<name>``: DIS at each preset, OpenCV contrib's DeepFlow,
Dual TV-L1, PCA-Flow, Farnebäck, sparse-to-dense and dense RLOF, at their defaults), on the same
pairs of the study's test worlds: the persistent worlds of KITTI's test trajectories 09 and 10,
rendered at 192 × 512 (``flow=dis``'s render size), ``--frames`` source frames per sequence
evenly spaced, each paired with its frames at offsets −2, −1, +1 and +2 (the study's offsets).

Per estimator and offset: EPE (mean end-point error, px at the render size) and Fl (KITTI's
outlier rate: EPE > 3 px and > 5 % of the exact flow's magnitude) by region of the renderer
(road, structure, moving objects, far field) and over all pixels, pooled pixel by pixel over the
pairs (:func:`mfg_lightning.metrics.flow_quality.flow_quality`, what ``flow_quality.md``'s DIS rows
use); and the estimator's time per pair in ms (the call alone, on one thread, wall time: the
machine may be shared; the CPU kind is in the environment table).

Every estimator is a stage cached as ``--work/<estimator>.json`` (with the workload's settings);
a rerun resumes where an interrupted one stopped, ``--fresh`` measures again. Written as one
section of ``<out>/flow_quality.md`` between ``<!-- flow-estimators:start -->`` and
``<!-- flow-estimators:end -->``.

``python bench/flow_estimators.py --poses-dir ../shared/data/kitti_odometry/poses`` (about
6 minutes on one core); ``--tiny`` for a smoke run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (
    DEFAULT_POSES_DIR,
    RESULTS_DIR,
    Report,
    add_common_arguments,
    fmt,
    markdown_table,
)

#: The marker of this script's section in flow_quality.md.
MARKER = "flow-estimators"
HEADING = "Every estimator on the same test pairs"
#: (label, flow config) of every estimator measured, in the table's order.
ESTIMATOR_RUNS = (
    ("DIS ultrafast", {"source": "dis", "preset": "ultrafast"}),
    ("DIS fast", {"source": "dis", "preset": "fast"}),
    ("DIS medium", {"source": "dis", "preset": "medium"}),
    ("DeepFlow", {"source": "deepflow"}),
    ("Dual TV-L1", {"source": "tvl1"}),
    ("PCA-Flow", {"source": "pcaflow"}),
    ("Farnebäck", {"source": "farneback"}),
    ("sparse to dense", {"source": "sparse_to_dense"}),
    ("dense RLOF", {"source": "rlof"}),
    ("learned (PWC-Net design)", {"source": "learned"}),
)
OFFSETS = (-2, -1, 1, 2)
RENDER_HW = (192, 512)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--poses-dir", type=Path, default=DEFAULT_POSES_DIR, help="KITTI's poses/")
    p.add_argument("--sequences", nargs="+", default=["09", "10"], help="test trajectories")
    p.add_argument("--frames", type=int, default=12, help="source frames per sequence")
    p.add_argument("--work", type=Path, default=RESULTS_DIR / "flow_estimators",
                   help="the stages' cached results")  # fmt: skip
    p.add_argument("--fresh", action="store_true", help="measure every stage again")
    p.add_argument("--whole-test", action="store_true",
                   help="also DIS medium and the learned flow on every +1 pair of the study's "
                   "test split (09, 10; minutes)")  # fmt: skip
    p.add_argument("--estimators", nargs="+", default=None,
                   help="only these stages (dis_medium, deepflow, ...); default: all")  # fmt: skip
    add_common_arguments(p)
    args = p.parse_args(argv)
    if args.tiny:
        args.frames = 2
    return args


def pairs_of(n_frames: int, sources: int) -> list[tuple[int, int]]:
    """``(source, target)`` of ``sources`` evenly spaced source frames of a trajectory of
    ``n_frames`` frames, each at every offset of :data:`OFFSETS` (frames 2 … n − 3 only, so
    that every offset exists)."""
    picks = np.linspace(2, n_frames - 3, sources).round().astype(int)
    return [(int(s), int(s) + o) for s in picks for o in OFFSETS]


class Scenes:
    """The test worlds, their rendered frames and exact flows, computed once for every
    estimator."""

    def __init__(self, poses_dir: Path, sequences: list[str], frames: int) -> None:
        import torch

        from mfg_lightning.scene import render, worlds
        from mfg_lightning.scene.camera import kitti_like_intrinsics
        from mfg_lightning.trajectory.pose_io import read_kitti_poses

        self.render = render
        self.intrinsics = kitti_like_intrinsics(*RENDER_HW)
        self.pairs: list[tuple[str, int, int]] = []
        self.worlds: dict[str, Any] = {}
        self.frames: dict[tuple[str, int], Any] = {}
        self.exact: dict[tuple[str, int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        for seq in sequences:
            poses = torch.as_tensor(read_kitti_poses(poses_dir / f"{seq}.txt"))
            self.worlds[seq] = worlds.World.generate(poses, seed=0, name=seq)
            self.pairs += [(seq, s, t) for s, t in pairs_of(len(poses), frames)]

    def frame(self, seq: str, i: int) -> Any:
        if (seq, i) not in self.frames:
            self.frames[seq, i] = self.render.render_frame(
                self.worlds[seq], i, self.intrinsics, *RENDER_HW
            )
        return self.frames[seq, i]

    def rgb(self, seq: str, i: int) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB of frame ``i``."""
        return np.ascontiguousarray(self.frame(seq, i).rgb.numpy().transpose(1, 2, 0))

    def truth(self, seq: str, s: int, t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The exact flow ``(H, W, 2)``, where it is known ``(H, W)``, and the regions."""
        if (seq, s, t) not in self.exact:
            a = self.frame(seq, s)
            e = self.render.exact_flow(self.worlds[seq], s, t, self.intrinsics, *RENDER_HW,
                                       source=a)  # fmt: skip
            flow = np.ascontiguousarray(e["flow"].numpy().transpose(1, 2, 0), dtype=np.float32)
            valid = e["flow_valid"].numpy().astype(bool) & np.isfinite(flow).all(2)
            self.exact[seq, s, t] = (np.where(valid[..., None], flow, 0.0), valid,
                                     a.region.numpy())  # fmt: skip
        return self.exact[seq, s, t]


def measure(scenes: Scenes, flow_cfg: dict) -> dict:
    """One estimator on every pair: summed quality per offset and region, ms per pair."""
    import cv2
    import torch

    from mfg_lightning.flow.estimators import parse_flow
    from mfg_lightning.metrics.flow_quality import QUALITY_REGIONS, flow_quality, summarize_quality

    cv2.setNumThreads(1)
    torch.set_num_threads(1)  # the learned network, on one core as OpenCV's
    estimator = parse_flow(flow_cfg, default="dis").estimator
    prepared: dict[tuple[str, int], np.ndarray] = {}
    stats = {o: np.zeros((len(QUALITY_REGIONS), 3)) for o in OFFSETS}
    seconds, nonfinite = [], 0
    for seq, s, t in scenes.pairs:
        for i in (s, t):
            if (seq, i) not in prepared:
                prepared[seq, i] = estimator.prepare(scenes.rgb(seq, i))
        start = time.perf_counter()
        est = np.asarray(estimator(prepared[seq, s], prepared[seq, t]), dtype=np.float32)
        seconds.append(time.perf_counter() - start)
        finite = np.isfinite(est).all(axis=2)
        nonfinite += int((~finite).sum())
        exact, valid, region = scenes.truth(seq, s, t)
        est = np.where(finite[..., None], est, 0.0)
        stats[t - s] += flow_quality(est, exact, valid & finite, region)
    pooled = sum(stats.values())
    return {
        "key": estimator.key(),
        "pairs": len(scenes.pairs),
        "ms_per_pair": 1000 * float(np.median(seconds)),
        "ms_per_pair_mean": 1000 * float(np.mean(seconds)),
        "nonfinite_pixels": nonfinite,
        "by_offset": {str(o): summarize_quality(stats[o]) for o in OFFSETS},
        "all_offsets": summarize_quality(pooled),
    }


#: The whole-test stage's estimators (label, flow config).
WHOLE_TEST_RUNS = (("DIS medium", {"source": "dis", "preset": "medium"}),
                   ("learned (PWC-Net design)", {"source": "learned"}))  # fmt: skip


def whole_test(poses_dir: Path, sequences: list[str], flow_cfg: dict) -> dict:
    """One estimator on every +1 pair of the study's test split (``dataset=synthetic
    trajectory=kitti``'s test worlds of ``sequences``, the pairs whose DIS quality
    ``flow_quality.md``'s first table gives): its quality pooled by region, computed through
    the data module's own preparation (rendered, estimated and cached on every core; a cached
    pair is read back)."""
    from mfg_lightning.data.rendered_preparation import prepare_pairs
    from mfg_lightning.data.synthetic import SyntheticDataModule

    dm = SyntheticDataModule(trajectory="kitti", poses_dir=str(poses_dir),
                             train_sequences=sequences[:1], test_sequences=sequences,
                             flow=flow_cfg, offsets=[1], scene_seed=0)  # fmt: skip
    ds = dm.dataset("test")
    done = prepare_pairs([ds])[0]
    quality = ds.quality(done.stats)
    return {"key": ds.flow_source.key(), "pairs": len(ds), "computed": done.pairs, **quality}


def _cell(q: dict | None, key: str, digits: int) -> str:
    return "–" if q is None or q.get(key) is None else fmt(q[key], digits)


def tables(results: dict[str, dict]) -> str:
    """The section's tables: by region over every offset, then EPE / Fl by offset."""
    from mfg_lightning.metrics.flow_quality import QUALITY_REGIONS

    head = ["estimator", "ms / pair"] + [f"{x} {r}" for r in QUALITY_REGIONS
                                          for x in ("EPE", "Fl %")]  # fmt: skip
    rows = []
    for label, r in results.items():
        q = r["all_offsets"]
        rows.append([label, fmt(r["ms_per_pair"], 1)]
                    + [c for reg in QUALITY_REGIONS
                       for c in (_cell(q[reg], "epe", 2), _cell(q[reg], "fl", 1))])  # fmt: skip
    by_offset = [
        [label] + [f"{_cell(r['by_offset'][str(o)]['all'], 'epe', 2)} / "
                   f"{_cell(r['by_offset'][str(o)]['all'], 'fl', 1)}" for o in OFFSETS]
        for label, r in results.items()
    ]  # fmt: skip
    return (
        "By region, every offset pooled (EPE in px at 192 × 512, Fl in %):\n\n"
        + markdown_table(head, rows)
        + "\nBy offset, all pixels (EPE px / Fl %):\n\n"
        + markdown_table(["estimator", *(f"{o:+d}" for o in OFFSETS)], by_offset)
    )


def main(argv: list[str] | None = None) -> None:
    from mfg_lightning.flow.estimators import parse_flow

    args = parse_args(argv)
    settings = {"sequences": args.sequences, "frames": args.frames, "render": list(RENDER_HW)}
    args.work.mkdir(parents=True, exist_ok=True)
    # made first, so that its environment's wall time covers the measurements
    report = Report("flow_quality", "Flow of rendered worlds", args.out)
    scenes: Scenes | None = None
    results: dict[str, dict] = {}
    for label, cfg in ESTIMATOR_RUNS:
        stem = cfg["source"] + (f"_{cfg['preset']}" if "preset" in cfg else "")
        if args.estimators is not None and stem not in args.estimators:
            continue
        path = args.work / f"{stem}{'_tiny' if args.tiny else ''}.json"
        cached = json.loads(path.read_text()) if path.is_file() and not args.fresh else None
        key = parse_flow(cfg, default="dis").estimator.key()  # (the learned one's weights)
        if cached is None or cached.get("settings") != settings or cached.get("key") != key:
            if scenes is None:
                scenes = Scenes(args.poses_dir, args.sequences, args.frames)
            print(f"{label}: {len(scenes.pairs)} pairs", flush=True)
            sized = {**cfg, "height": RENDER_HW[0], "width": RENDER_HW[1]}
            start = time.perf_counter()
            cached = {"settings": settings, **measure(scenes, sized)}
            # the stage's wall time (a resumed run's environment counts only what it measured)
            cached["seconds"] = time.perf_counter() - start
            path.write_text(json.dumps(cached, indent=1) + "\n")
        results[label] = cached
    pairs = next(iter(results.values()))["pairs"]
    staged = sum(r.get("seconds", 0.0) for r in results.values())
    report.add(
        f"{pairs} pairs of the test worlds ({', '.join(args.sequences)}; {args.frames} source "
        f"frames per sequence, offsets {', '.join(f'{o:+d}' for o in OFFSETS)}), rendered at "
        f"{RENDER_HW[0]} × {RENDER_HW[1]}; every estimator at its defaults (DIS at each preset) "
        "on the same pairs, against the renderer's exact flow. ms / pair: the estimator's call "
        "alone, median over the pairs, one OpenCV thread and one torch thread (the learned "
        "network: `flow=learned`, the shipped weights, `docs/flow.md`); "
        "`bench/flow_estimators.py` (stage "
        f"results in `bench/results/flow_estimators/`, measured in {staged:.0f} s of wall time "
        "in all, the first stage's rendering included).\n\n" + tables(results)
    )
    if args.whole_test or whole_test_path(args).is_file():
        report.add(whole_test_section(args))
    report.write_section(MARKER, HEADING)


def whole_test_path(args: argparse.Namespace) -> Path:
    """Where the whole-test stage is cached."""
    return args.work / f"whole_test{'_tiny' if args.tiny else ''}.json"


def whole_test_section(args: argparse.Namespace) -> str:
    """The whole-test stage (cached as ``--work/whole_test.json``; ``--whole-test`` measures
    what is missing), as a paragraph and a table."""
    from mfg_lightning.flow.estimators import parse_flow
    from mfg_lightning.metrics.flow_quality import QUALITY_REGIONS

    path = whole_test_path(args)
    cached = json.loads(path.read_text()) if path.is_file() else {}
    for label, cfg in WHOLE_TEST_RUNS:
        key = parse_flow(cfg, default="dis").estimator.key()
        entry = cached.get(label)
        if args.whole_test and (entry is None or entry.get("estimator_key") != key):
            start = time.perf_counter()
            entry = whole_test(args.poses_dir, args.sequences, cfg)
            entry["estimator_key"], entry["seconds"] = key, time.perf_counter() - start
            cached[label] = entry
            path.write_text(json.dumps(cached, indent=1) + "\n")
    rows = [[label, str(r["pairs"])] + [_cell(r["regions"][g], "epe", 2) for g in QUALITY_REGIONS]
            + [_cell(r["regions"]["all"], "fl", 1)] for label, r in cached.items()]  # fmt: skip
    head = ["estimator", "pairs", *(f"EPE {g}" for g in QUALITY_REGIONS), "Fl % all"]
    return (
        "### Every +1 pair of the study's test split\n\n"
        f"Every +1 pair of the test worlds of {', '.join(args.sequences)} as the study renders "
        "them (`dataset=synthetic trajectory=kitti`'s test split, its worlds' own seed: the "
        "pairs of the first table's `test` row), through the data module's preparation "
        "(`--whole-test`; cached as `bench/results/flow_estimators/whole_test.json`). EPE in "
        "px at 192 × 512:\n\n" + markdown_table(head, rows)
    )


if __name__ == "__main__":
    main()
