"""The DIS source's own stages and ``flow_quality.md``: every frame of 00–10 rendered and its
pairs estimated into the dataset's cache (:func:`stage_render`), the CPU time of each step of a
pair (:func:`stage_breakdown`), data-loading passes over the cache (:func:`stage_loading`), and
the report of the estimated flow's quality by region and of the cost (:func:`write_flow_quality`).
Each stage caches its result under ``--work`` (:mod:`.settings`)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from _common import Report, cpu_seconds, fmt, load_average, markdown_table

from .settings import datamodule_for, frames_tag, read_stage, write_stage


def stage_render(args: argparse.Namespace, max_frames: int | None) -> dict:
    """Render every frame of 00–10 and estimate the DIS flow of every pair into the cache.

    The cost is recorded per part and run (``render-<frames>.json``: the seconds and pairs of
    the train + validation part and of the test part), so an interrupted run keeps the pairs
    and what it measured, and the next one adds to it.
    """
    path = args.work / f"render-{frames_tag(max_frames)}.json"
    ledger = read_stage(path) or {"runs": []}
    if ledger.get("done"):
        return ledger
    _, dm = datamodule_for(args, "dis", max_frames)
    parts = {}
    for part in ("train+val", "test"):
        ds = dm.build_dataset(part)
        parts[part] = {
            "pairs": len(ds),
            "frames": sum(int(t.shape[0]) for t in ds.trajectories.values()),
        }
        load_start = load_average()
        start, cpu_start = time.perf_counter(), cpu_seconds()
        n = ds.precompute_flow(progress=not args.tiny, workers=args.workers)
        if n:
            ledger["runs"].append(
                {
                    "part": part,
                    "pairs": n,
                    "frames": ds.rendered_frames,
                    "seconds": time.perf_counter() - start,
                    # this process and its finished workers: what contention does not change
                    "cpu_seconds": cpu_seconds() - cpu_start,
                    "workers": args.workers,
                    "load_start": load_start,
                    "load_end": load_average(),
                }
            )
            write_stage(path, ledger)
    ledger["parts"] = parts
    ledger["image_hw"] = list(dm.build_dataset("test").image_hw)
    ledger["preset"] = args.dis_preset
    ledger["max_frames"] = max_frames
    # The quality summaries and the pictures (every pair is cached now).
    dm.prepare_data()
    ledger["quality"] = {
        split: json.loads(dm.quality_path(split).read_text()) for split in ("train", "val", "test")
    }
    ledger["done"] = True
    write_stage(path, ledger)
    return ledger


def stage_breakdown(args: argparse.Namespace, max_frames: int | None, pairs: int = 20) -> dict:
    """CPU time (``time.process_time``, one thread: what contention does not change) of each
    step of a pair, on ``pairs`` consecutive pairs of sequence 00 (training data), rendered
    into a scratch cache."""
    path = args.work / f"breakdown-{frames_tag(max_frames)}.json"
    done = read_stage(path)
    if done:
        return done
    import cv2

    from mfg_lightning.scene import render

    threads = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    _, dm = datamodule_for(args, "dis", max_frames)
    dm.cache_dir = str(args.work / "breakdown-cache")
    ds = dm.build_dataset("train+val")
    seq = next(iter(ds.trajectories))
    first = ds.sequences()[seq][0]
    clock = time.process_time
    spent = {"render": 0.0, "exact flow": 0.0, "DIS": 0.0, "quality, resize": 0.0, "write": 0.0}
    t = clock()
    a = ds.render(seq, ds.samples[first][1])
    spent["render"] += clock() - t  # the first frame: one render per pair from here on
    for i in range(first, first + pairs):
        _, src, tgt = ds.samples[i]
        t = clock()
        b = ds.render(seq, tgt)
        spent["render"] += clock() - t
        t = clock()
        world, K, hw = ds.world(seq), ds.image_intrinsics, ds.image_hw
        render.exact_flow(world, src, tgt, K, *hw, source=a.rendered, target=b.rendered)
        spent["exact flow"] += clock() - t
        t = clock()
        ds.estimator(a.image, b.image)
        spent["DIS"] += clock() - t
        t = clock()
        pair = ds.compute_pair(seq, src, tgt, a, b)  # exact flow + DIS again, then the rest
        spent["quality, resize"] += clock() - t
        t = clock()
        ds._store(i, pair)
        spent["write"] += clock() - t
        a = b
    spent["quality, resize"] -= spent["exact flow"] + spent["DIS"]
    torch.set_num_threads(threads[0])
    cv2.setNumThreads(threads[1])
    result = {
        "pairs": pairs,
        "sequence": seq,
        "ms_per_pair": {k: 1e3 * v / pairs for k, v in spent.items()},
        "image_hw": list(ds.image_hw),
    }
    write_stage(path, result)
    return result


def stage_loading(args: argparse.Namespace, max_frames: int | None) -> dict:
    """Data-loading passes over the cached training split (what every epoch after the first
    costs), against the first pass (rendering and estimating, from ``render.json``)."""
    path = args.work / f"loading-{frames_tag(max_frames)}.json"
    done = read_stage(path)
    if done:
        return done
    from torch.utils.data import DataLoader

    from mfg_lightning.data.base import collate_samples

    cfg, dm = datamodule_for(args, "dis", max_frames)
    ds = dm.dataset("train")
    passes = []
    for _ in range(2):
        loader = DataLoader(ds, batch_size=cfg.dataset.batch_size, collate_fn=collate_samples)
        start = time.perf_counter()
        n = sum(b["flow"].shape[0] for b in loader)
        passes.append(time.perf_counter() - start)
    result = {
        "samples": n,
        "cached_passes": passes,
        "rendered": ds.rendered_frames,
        "load": load_average(),
    }
    write_stage(path, result)
    return result


QUALITY_ORDER = ("road", "structure", "moving", "far", "all")


def frames_note(max_frames: int | None) -> str:
    return f"the first {max_frames} frames of every sequence, " if max_frames else ""


def _value(regions: dict | None, region: str, key: str, digits: int) -> str:
    """One cell of :func:`quality_table` (``–``: a split measured before noc was scored, or a
    region without pixels)."""
    value = None if regions is None else regions[region][key]
    return "–" if value is None else fmt(value, digits)


def quality_table(rendered: dict) -> str:
    """Two rows per split: its non-occluded pixels (``noc``: visible in the second frame and
    inside it) and all pixels whose exact flow is known (``all``), each with its pixels per
    pair, EPE and Fl by region and the non-finite estimated pixels."""
    hw = "×".join(str(x) for x in rendered["image_hw"])
    header = ["split", "pixels", "DIS preset", "render size", "pixels / pair"]
    for region in QUALITY_ORDER:
        header += [f"EPE {region} (px)", f"Fl {region} (%)"]
    header.append("non-finite px")
    body = []
    for split, q in rendered["quality"].items():
        pairs = max(rendered["parts"]["test" if split == "test" else "train+val"]["pairs"], 1)
        for name, regions in (("noc", q.get("regions_noc")), ("all", q["regions"])):
            per_pair = "–" if regions is None else fmt(regions["all"]["pixels"] / pairs, 0)
            row = [split, name, rendered["preset"], hw, per_pair]
            for region in QUALITY_ORDER:
                row += [_value(regions, region, "epe", 2), _value(regions, region, "fl", 1)]
            row.append(str(q["nonfinite_pixels"]))
            body.append(row)
    return markdown_table(header, body)


def full_split_pairs(poses_dir: Path) -> int:
    """Pairs of the whole 00–08 split (train + validation: every frame but the last)."""
    return sum(len((poses_dir / f"{s:02d}.txt").read_text().splitlines()) - 1 for s in range(9))


def breakdown_section(breakdown: dict, rendered: dict, train_pairs: int) -> str:
    ms = breakdown["ms_per_pair"]
    total = sum(ms.values())
    rows = [[k, fmt(v, 1), f"{100 * v / total:.0f} %"] for k, v in ms.items()]
    rows.append(["**total**", fmt(total, 1), "100 %"])
    size = "×".join(str(x) for x in breakdown["image_hw"])
    return (
        markdown_table(["step", "CPU ms / pair", "share"], rows)
        + f"\n{breakdown['pairs']} consecutive pairs of sequence {breakdown['sequence']} at "
        f"{size}, one thread, `time.process_time` (CPU time: what a shared machine's "
        "contention does not change, unlike the wall time below). A frame is rendered once per "
        "pair (each is the target of one pair and the source of the next). The whole 00–08 "
        f"split ({train_pairs} pairs) at this CPU cost: "
        f"{total * train_pairs / 6e4:.0f} CPU-minutes, "
        f"**{total * train_pairs / 12e4:.0f} min on 2 cores** with 2 processes "
        "(`dataset.prepare_workers`, by default every core: chunks of frames, one thread "
        "each; target ≤ 30 min)."
    )


def cost_section(rendered: dict, loading: dict | None, train_pairs: int) -> str:
    runs = rendered["runs"]
    seconds = sum(r["seconds"] for r in runs)
    pairs = sum(r["pairs"] for r in runs)
    frames = sum(r["frames"] for r in runs)
    per_pair = seconds / max(pairs, 1)
    rows = [
        [
            r["part"],
            r["pairs"],
            r["frames"],
            r["workers"],
            fmt(r["seconds"] / 60, 1),
            fmt(1e3 * r["seconds"] / max(r["pairs"], 1), 1),
            f"{r['load_start']} → {r['load_end']}",
        ]
        for r in runs
    ]
    text = markdown_table(
        ["part", "pairs", "frames rendered", "processes", "minutes", "ms / pair", "load average"],
        rows,
    )
    cpu = [r for r in runs if r.get("cpu_seconds")]
    if cpu:
        cpu_per_pair = sum(r["cpu_seconds"] for r in cpu) / sum(r["pairs"] for r in cpu)
        text += (
            f"\nCPU time (user + system, every process): {1e3 * cpu_per_pair:.1f} ms per pair, "
            f"so the 00–08 split takes **{cpu_per_pair * train_pairs / 120:.1f} min on 2 idle "
            "cores** whatever the load was.\n"
        )
    text += (
        f"\nIn all {frames} frames rendered and {pairs} pairs estimated in {seconds / 60:.1f} min "
        f"({1e3 * per_pair:.1f} ms per pair: rendering, exact flow, DIS, the quality, the "
        "resizing and the cache write; one torch and OpenCV thread per process). The whole "
        f"00–08 split (train + validation, {train_pairs} pairs) at that contended rate: "
        f"**{per_pair * train_pairs / 60:.1f} min** (target ≤ 30 min on 2 cores). Load average "
        "(1/5/15 min) at the start → end of each part above: the machine is shared."
    )
    if loading:
        first = per_pair * loading["samples"]
        cached = min(loading["cached_passes"])
        text += (
            f"\n\nData-loading pass over the training split ({loading['samples']} samples, batch "
            f"16, `num_workers=0`): first pass (render + estimate + write, at the rate above) "
            f"{first:.0f} s; a pass over the cache {cached:.2f} s "
            f"({', '.join(f'{x:.2f}' for x in loading['cached_passes'])} s for two passes; "
            f"{loading['rendered']} frames rendered during them): "
            f"**{first / max(cached, 1e-9):.0f}× faster** (target ≥ 50×)."
        )
    return text


def write_flow_quality(
    args: argparse.Namespace,
    rendered: dict,
    loading: dict | None,
    breakdown: dict | None,
    started: float | None = None,
) -> Path:
    """``flow_quality.md``: the DIS flow's quality by region and the cost of the split
    (``started``: when the measurements began, ``time.time()``, for the environment's wall
    time; None: now)."""
    quality = Report(
        "flow_quality",
        "Flow of rendered worlds: quality of DIS against the exact flow, and its cost",
        args.out,
    )
    if started is not None:
        quality.started = started
    quality.add(
        "Worlds rendered along the real KITTI trajectories 00–10 "
        f"(`flow=dis flow.preset={rendered['preset']}`, "
        f"{frames_note(rendered['max_frames'])}"
        "seed 0), DIS at the render size, compared with the exact flow from the same ray "
        "casts at that size. EPE: mean end-point error (pixels of the render size). Fl: "
        "KITTI's outlier rate, pixels with EPE > 3 px and > 5 % of the exact flow's "
        "magnitude. Pooled pixel by pixel over the pairs "
        "(`quality-<split>-<pairs>pairs-<digest>.json` beside the cache), as KITTI 2015 scores "
        "flow: on the non-occluded pixels (`noc`: the point visible in the second frame and "
        "inside it) and on all pixels whose exact flow is known (`all`: occluded and "
        "out-of-frame ones included; the renderer marks them, `docs/flow.md`). Regions are the "
        "renderer's: road, structure (facades, parked cars, crates), moving objects, far "
        "field (sky)."
    )
    quality.add("## Quality by region\n\n" + quality_table(rendered))
    full = full_split_pairs(args.poses_dir)
    steps = breakdown_section(breakdown, rendered, full)
    quality.add("## CPU time per pair, by step\n\n" + steps)
    quality.add(
        "## Cost of rendering and estimating, and of a cached pass\n\n"
        + cost_section(rendered, loading, full)
    )
    return quality.write()
