"""Which optical-flow estimator gives the rendered worlds' best flow, and at what cost?

Every estimator the framework has (``flow=<name>``: DIS at each preset, OpenCV contrib's DeepFlow,
Dual TV-L1, PCA-Flow, Farnebäck, sparse-to-dense and dense RLOF, at their defaults), on the same
pairs of persistent worlds along KITTI's test trajectories 09 and 10, rendered at 192 × 512
(``flow=dis``'s render size), ``--frames`` source frames per sequence evenly spaced, each paired
with its frames at offsets −2, −1, +1 and +2 (the study's offsets). Two sets of worlds
(``--worlds``): ``seed0``, the worlds of scene seed 0 (disjoint from every training world, but
*not* the study's test worlds), and ``study``, the study's test worlds themselves (``dataset=
synthetic trajectory=kitti``'s test split: scene seed 0 + 7919, :func:`study_test_worlds`).

Per estimator and offset: EPE (mean end-point error, px at the render size) and Fl (KITTI's
outlier rate: EPE > 3 px and > 5 % of the exact flow's magnitude) by region of the renderer
(road, structure, moving objects, far field) and over the whole image, on KITTI's two sets of
pixels: ``noc``, the non-occluded pixels (visible in the second frame and inside it), and
``all``, every pixel whose exact flow is known (occluded and out-of-frame ones included), pooled
pixel by pixel over the pairs (:func:`mfg_lightning.metrics.flow_quality.flow_quality`, what
``flow_quality.md``'s DIS rows use); and the estimator's time per pair in ms (the call alone, on
one thread, wall time: the machine may be shared; the CPU kind is in the environment table).

Every estimator and set of worlds is a stage cached as ``--work/<estimator>[_study].json``
(with the workload's settings); a rerun resumes where an interrupted one stopped, ``--fresh``
measures again. Written as one section of ``<out>/flow_quality.md`` between
``<!-- flow-estimators:start -->`` and ``<!-- flow-estimators:end -->``.

``python bench/flow_estimators.py --poses-dir ../shared/data/kitti_odometry/poses`` (about
6 minutes per set of worlds on one core, Dual TV-L1 most of it); ``--whole-test`` adds DIS
medium and the learned flow on every +1 pair of the study's test split; ``--tiny`` for a smoke
run.
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
#: The sets of worlds (``--worlds``): their description and stage-file suffix.
WORLD_SETS = {
    "seed0": ("scene seed 0's worlds: disjoint from every training world, but not the study's "
              "test worlds (those are the next set's)", ""),
    "study": ("the study's test worlds: those of `dataset=synthetic trajectory=kitti`'s test "
              "split, scene seed 0 + 7919", "_study"),
}  # fmt: skip
#: What a stage's results hold (a cached stage of another scoring is measured again).
SCORING = "noc+all"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--poses-dir", type=Path, default=DEFAULT_POSES_DIR, help="KITTI's poses/")
    p.add_argument("--sequences", nargs="+", default=["09", "10"], help="test trajectories")
    p.add_argument("--frames", type=int, default=12, help="source frames per sequence")
    p.add_argument("--worlds", nargs="+", choices=list(WORLD_SETS), default=list(WORLD_SETS),
                   help="the sets of worlds measured: seed0 (scene seed 0) and/or study (the "
                   "study's test worlds); default both")  # fmt: skip
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


def study_test_worlds(poses_dir: Path, sequences: list[str]) -> tuple[dict[str, Any], int]:
    """The trajectories (by name) and the world seed of the study's test split: what
    ``dataset=synthetic trajectory=kitti test_sequences=<sequences>`` renders at the default
    ``scene_seed`` (0, ``conf/dataset/synthetic.yaml``; the test split adds 7919 to it)."""
    from mfg_lightning.data.synthetic import SyntheticDataModule

    dm = SyntheticDataModule(trajectory="kitti", poses_dir=str(poses_dir),
                             train_sequences=sequences[:1], test_sequences=sequences,
                             flow={"source": "dis"}, scene_seed=0)  # fmt: skip
    trajectories, _, common = dm.split_spec("test")
    return trajectories, int(common["seed"])


class Scenes:
    """One set of worlds (:data:`WORLD_SETS`), their rendered frames and exact flows, computed
    once for every estimator."""

    def __init__(self, poses_dir: Path, sequences: list[str], frames: int, worlds: str) -> None:
        import torch

        from mfg_lightning.scene import render
        from mfg_lightning.scene import worlds as scene_worlds
        from mfg_lightning.scene.camera import kitti_like_intrinsics
        from mfg_lightning.trajectory.pose_io import read_kitti_poses

        self.render = render
        self.intrinsics = kitti_like_intrinsics(*RENDER_HW)
        self.pairs: list[tuple[str, int, int]] = []
        self.worlds: dict[str, Any] = {}
        self.frames: dict[tuple[str, int], Any] = {}
        self.exact: dict[tuple[str, int, int], dict[str, np.ndarray]] = {}
        if worlds == "study":
            trajectories, seed = study_test_worlds(poses_dir, sequences)
        else:
            seed = 0
            trajectories = {seq: torch.as_tensor(read_kitti_poses(poses_dir / f"{seq}.txt"))
                            for seq in sequences}  # fmt: skip
        self.seed = seed
        for seq, poses in trajectories.items():
            self.worlds[seq] = scene_worlds.World.generate(poses, seed=seed, name=seq)
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

    def truth(self, seq: str, s: int, t: int) -> dict[str, np.ndarray]:
        """The exact flow ``"flow"`` ``(H, W, 2)`` (0 where unknown), where it is known
        ``"valid"``, its visibility codes ``"visibility"``
        (:func:`~mfg_lightning.metrics.flow_quality.visibility_codes`) and the regions
        ``"region"``, ``(H, W)`` each."""
        from mfg_lightning.metrics.flow_quality import visibility_codes

        if (seq, s, t) not in self.exact:
            a = self.frame(seq, s)
            e = self.render.exact_flow(self.worlds[seq], s, t, self.intrinsics, *RENDER_HW,
                                       source=a, target=self.frame(seq, t))  # fmt: skip
            flow = np.ascontiguousarray(e["flow"].numpy().transpose(1, 2, 0), dtype=np.float32)
            valid = e["flow_valid"].numpy().astype(bool) & np.isfinite(flow).all(2)
            self.exact[seq, s, t] = {
                "flow": np.where(valid[..., None], flow, 0.0),
                "valid": valid,
                "visibility": visibility_codes(
                    valid, e["out_of_frame"].numpy(), e["occluded"].numpy()
                ),
                "region": a.region.numpy(),
            }
        return self.exact[seq, s, t]


def measure(scenes: Scenes, flow_cfg: dict) -> dict:
    """One estimator on every pair: summed quality per offset, set of pixels (noc, all) and
    region, the pairs' hidden pixel counts, ms per pair."""
    import cv2
    import torch

    from mfg_lightning.flow.estimators import parse_flow
    from mfg_lightning.metrics.flow_quality import (
        OCCLUDED,
        OUT_OF_FRAME,
        QUALITY_REGIONS,
        QUALITY_SETS,
        VISIBLE,
        flow_quality,
        summarize_noc_all,
    )

    cv2.setNumThreads(1)
    torch.set_num_threads(1)  # the learned network, on one core as OpenCV's
    estimator = parse_flow(flow_cfg, default="dis").estimator
    prepared: dict[tuple[str, int], np.ndarray] = {}
    stats = {o: np.zeros((len(QUALITY_SETS), len(QUALITY_REGIONS), 3)) for o in OFFSETS}
    seconds, nonfinite, occluded, out_of_frame = [], 0, 0, 0
    for seq, s, t in scenes.pairs:
        for i in (s, t):
            if (seq, i) not in prepared:
                prepared[seq, i] = estimator.prepare(scenes.rgb(seq, i))
        start = time.perf_counter()
        est = np.asarray(estimator(prepared[seq, s], prepared[seq, t]), dtype=np.float32)
        seconds.append(time.perf_counter() - start)
        finite = np.isfinite(est).all(axis=2)
        nonfinite += int((~finite).sum())
        truth = scenes.truth(seq, s, t)
        est = np.where(finite[..., None], est, 0.0)
        codes = truth["visibility"]
        stats[t - s] += flow_quality(est, truth["flow"], truth["valid"] & finite, truth["region"],
                                     noc=codes == VISIBLE)  # fmt: skip
        occluded += int((codes == OCCLUDED).sum())
        out_of_frame += int((codes == OUT_OF_FRAME).sum())
    pooled = sum(stats.values())
    return {
        "key": estimator.key(),
        "pairs": len(scenes.pairs),
        "world_seed": scenes.seed,
        "ms_per_pair": 1000 * float(np.median(seconds)),
        "ms_per_pair_mean": 1000 * float(np.mean(seconds)),
        "nonfinite_pixels": nonfinite,
        "occluded_pixels": occluded,
        "out_of_frame_pixels": out_of_frame,
        "known_pixels": int(sum(scenes.truth(*p)["valid"].sum() for p in scenes.pairs)),
        "by_offset": {str(o): summarize_noc_all(stats[o]) for o in OFFSETS},
        "all_offsets": summarize_noc_all(pooled),
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


def _by_set(q: dict) -> list[tuple[str, dict | None]]:
    """``[("noc", regions), ("all", regions)]`` of a pooled quality
    (:func:`~mfg_lightning.metrics.flow_quality.summarize_noc_all`; None: a stage from before
    noc was scored)."""
    return [("noc", q.get("regions_noc")), ("all", q.get("regions"))]


def _region_cells(regions: dict | None) -> list[str]:
    """EPE and Fl of every region of ``regions`` (``{region: {"epe", "fl", ...}}``)."""
    from mfg_lightning.metrics.flow_quality import QUALITY_REGIONS

    return [c for g in QUALITY_REGIONS
            for c in (_cell(regions and regions[g], "epe", 2),
                      _cell(regions and regions[g], "fl", 1))]  # fmt: skip


def _region_head() -> list[str]:
    from mfg_lightning.metrics.flow_quality import QUALITY_REGIONS

    names = [r if r != "all" else "whole image" for r in QUALITY_REGIONS]
    return [f"{x} {r}" for r in names for x in ("EPE", "Fl %")]


def tables(results: dict[str, dict]) -> str:
    """The tables of one set of worlds: by region over every offset, then EPE / Fl by offset;
    a row per estimator and set of pixels (``noc``, ``all``)."""
    head = ["estimator", "pixels", "ms / pair", *_region_head()]
    rows = [[label, name, fmt(r["ms_per_pair"], 1), *_region_cells(q)]
            for label, r in results.items()
            for name, q in _by_set(r["all_offsets"])]  # fmt: skip
    by_offset = [
        [label, name] + [f"{_cell(q and q['all'], 'epe', 2)} / {_cell(q and q['all'], 'fl', 1)}"
                         for q in (dict(_by_set(r["by_offset"][str(o)]))[name]
                                   for o in OFFSETS)]
        for label, r in results.items() for name in ("noc", "all")
    ]  # fmt: skip
    return (
        "By region, every offset pooled (EPE in px at 192 × 512, Fl in %; pixels: `noc` the "
        "non-occluded ones, `all` every pixel whose exact flow is known):\n\n"
        + markdown_table(head, rows)
        + "\nBy offset, the whole image (EPE px / Fl %):\n\n"
        + markdown_table(["estimator", "pixels", *(f"{o:+d}" for o in OFFSETS)], by_offset)
    )


def hidden_share(result: dict) -> str:
    """``x % occluded and y % out of frame`` of the pixels whose exact flow is known."""
    known = max(result.get("known_pixels", 0), 1)
    return (f"{100 * result['occluded_pixels'] / known:.1f} % occluded and "
            f"{100 * result['out_of_frame_pixels'] / known:.1f} % out of frame")  # fmt: skip


def run_stages(args: argparse.Namespace, worlds: str) -> dict[str, dict]:
    """Every estimator on the pairs of one set of worlds (:data:`WORLD_SETS`), each read from
    its stage file when that was measured with the same settings and estimator, else measured
    (and written)."""
    from mfg_lightning.flow.estimators import parse_flow

    settings = {"sequences": args.sequences, "frames": args.frames, "render": list(RENDER_HW),
                "worlds": worlds, "scoring": SCORING}  # fmt: skip
    suffix = WORLD_SETS[worlds][1] + ("_tiny" if args.tiny else "")
    scenes: Scenes | None = None
    results: dict[str, dict] = {}
    for label, cfg in ESTIMATOR_RUNS:
        stem = cfg["source"] + (f"_{cfg['preset']}" if "preset" in cfg else "")
        if args.estimators is not None and stem not in args.estimators:
            continue
        path = args.work / f"{stem}{suffix}.json"
        cached = json.loads(path.read_text()) if path.is_file() and not args.fresh else None
        key = parse_flow(cfg, default="dis").estimator.key()  # (the learned one's weights)
        if cached is None or cached.get("settings") != settings or cached.get("key") != key:
            if scenes is None:
                scenes = Scenes(args.poses_dir, args.sequences, args.frames, worlds)
            print(f"{label} ({worlds}): {len(scenes.pairs)} pairs", flush=True)
            sized = {**cfg, "height": RENDER_HW[0], "width": RENDER_HW[1]}
            start = time.perf_counter()
            cached = {"settings": settings, **measure(scenes, sized)}
            # the stage's wall time (a resumed run's environment counts only what it measured)
            cached["seconds"] = time.perf_counter() - start
            path.write_text(json.dumps(cached, indent=1) + "\n")
        results[label] = cached
    return results


def worlds_section(args: argparse.Namespace, worlds: str, results: dict[str, dict]) -> str:
    """One set of worlds' paragraph and tables."""
    first = next(iter(results.values()))
    staged = sum(r.get("seconds", 0.0) for r in results.values())
    return (
        f"### {'The study' if worlds == 'study' else 'Scene seed 0'}'s worlds of "
        f"{', '.join(args.sequences)}\n\n"
        f"{first['pairs']} pairs ({', '.join(args.sequences)}; {args.frames} source frames "
        f"per sequence, offsets {', '.join(f'{o:+d}' for o in OFFSETS)}; world seed "
        f"{first['world_seed']}) of {WORLD_SETS[worlds][0]}; rendered at {RENDER_HW[0]} × "
        f"{RENDER_HW[1]}. Of the pixels whose exact flow is known, {hidden_share(first)} "
        "(`noc` leaves them out). Every estimator at its defaults (DIS at each preset) on the "
        "same pairs, against the renderer's exact flow. ms / pair: the estimator's call alone, "
        "median over the pairs, one OpenCV thread and one torch thread (the learned network: "
        "`flow=learned`, the shipped weights, `docs/flow.md`); measured in "
        f"{staged:.0f} s of wall time in all, the first stage's rendering included.\n\n"
        + tables(results)
    )


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    # made first, so that its environment's wall time covers the measurements
    report = Report("flow_quality", "Flow of rendered worlds", args.out)
    report.add(
        "Every estimator on the same pairs along KITTI's test trajectories, on each set of "
        "worlds measured: `bench/flow_estimators.py` (stage results in "
        "`bench/results/flow_estimators/`). EPE and Fl as KITTI 2015 gives them: on the "
        "non-occluded pixels (`noc`: the point visible in the second frame, inside it) and on "
        "all pixels with known flow (`all`: occluded and out-of-frame ones included; the "
        "renderer marks them, `docs/flow.md`)."
    )
    for worlds in args.worlds:
        report.add(worlds_section(args, worlds, run_stages(args, worlds)))
    if args.whole_test or whole_test_path(args).is_file():
        report.add(whole_test_section(args))
    report.write_section(MARKER, HEADING)


def whole_test_path(args: argparse.Namespace) -> Path:
    """Where the whole-test stage is cached."""
    return args.work / f"whole_test{'_tiny' if args.tiny else ''}.json"


def whole_test_section(args: argparse.Namespace) -> str:
    """The whole-test stage (cached as ``--work/whole_test.json``; ``--whole-test`` measures
    what is missing, or was measured before noc was scored), as a paragraph and a table."""
    from mfg_lightning.flow.estimators import parse_flow

    path = whole_test_path(args)
    cached = json.loads(path.read_text()) if path.is_file() else {}
    for label, cfg in WHOLE_TEST_RUNS:
        key = parse_flow(cfg, default="dis").estimator.key()
        entry = cached.get(label)
        stale = entry is None or entry.get("estimator_key") != key or "regions_noc" not in entry
        if args.whole_test and stale:
            start = time.perf_counter()
            entry = whole_test(args.poses_dir, args.sequences, cfg)
            entry["estimator_key"], entry["seconds"] = key, time.perf_counter() - start
            cached[label] = entry
            path.write_text(json.dumps(cached, indent=1) + "\n")
    rows = [[label, name, str(r["pairs"]), *_region_cells(q)]
            for label, r in cached.items() for name, q in _by_set(r)]  # fmt: skip
    _, seed = study_test_worlds(args.poses_dir, args.sequences)
    return (
        "### Every +1 pair of the study's test split\n\n"
        f"Every +1 pair of the study's test worlds of {', '.join(args.sequences)} (world seed "
        f"{seed}: `dataset=synthetic trajectory=kitti`'s test split, the pairs of the first "
        "table's `test` row), through the data module's preparation (`--whole-test`; cached "
        "as `bench/results/flow_estimators/whole_test.json`; `–`: measured before noc was "
        "scored). EPE in px at 192 × 512, Fl in %:\n\n"
        + markdown_table(["estimator", "pixels", "pairs", *_region_head()], rows)
    )


if __name__ == "__main__":
    main()
