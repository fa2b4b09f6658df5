"""S9 and S10, the object sentences, on the exact-flow Table-2-sized models' object masks and
velocities (every seed, per-pair counts: t over the seeds plus the paired bootstrap)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from mfg_lightning.core.tables import fmt
from mfg_lightning.study.intervals import FLOORS, INCONCLUSIVE, bootstrap_se, interval
from mfg_lightning.study.parts import MIN_SEEDS, Judged, Part, Settled, few_seeds
from mfg_lightning.study.quotes import SENTENCES
from mfg_lightning.study.render import paragraph

__all__ = ["object_sentences", "velocity_bins"]


def _counts(pairs: Mapping[str, list]) -> tuple[np.ndarray, ...]:
    return tuple(np.asarray(pairs[k], dtype=float) for k in ("tp", "fp", "fn"))


def _pooled(counts: tuple[np.ndarray, ...], key: str, idx: np.ndarray | None = None) -> Any:
    """IoU or precision pooled over the pairs (``idx``: ``(draws, n)`` resamples, one value
    each; None: all pairs once) from per-pair pixel counts; NaN where nothing was counted."""
    tp, fp, fn = counts if idx is None else (c[idx] for c in counts)
    axis = -1
    den = tp.sum(axis) + fp.sum(axis) + (fn.sum(axis) if key == "iou" else 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, tp.sum(axis) / den, np.nan)


def _mask_part(seeds: Mapping[int, dict], key: str, label: str) -> Part:
    if len(seeds) < MIN_SEEDS:
        return Part(label, None, 0.0, ">=", floor=few_seeds(len(seeds)))
    vals, ses = [], []
    for s, r in sorted(seeds.items()):
        f = _counts(r["objects"]["pairs"]["filters"])
        t = _counts(r["objects"]["pairs"]["threshold"])
        d = float(_pooled(f, key) - _pooled(t, key))
        if not math.isfinite(d):
            continue
        vals.append(d)
        ses.append(
            bootstrap_se(lambda i, f=f, t=t: _pooled(f, key, i) - _pooled(t, key, i), len(f[0]),
                         seed=s)
        )  # fmt: skip
    return Part(label, interval(vals, ses), 0.0, ">=", domain=(-1.0, 1.0), strict=True)


def velocity_bins(r: dict) -> list[dict[str, Any]]:
    """S10's bins of one seed: per object size × speed bin, the test pairs with objects in it,
    the pixels, and the filters' and the threshold's pooled velocity error (px/frame)."""
    o = r["objects"]
    sizes, speeds = o["size_bins"], o["speed_bins"]
    f, t = o["pairs"]["filters"], o["pairs"]["threshold"]
    pix = np.asarray(f["pixels"], dtype=float)
    ef, et = np.asarray(f["err"], dtype=float), np.asarray(t["err"], dtype=float)
    out = []
    for b in range(pix.shape[1]):
        i, k = divmod(b, len(speeds) - 1)
        n = pix[:, b].sum()
        out.append({
            "size": (sizes[i], sizes[i + 1]), "speed": (speeds[k], speeds[k + 1]),
            "pairs": int((pix[:, b] > 0).sum()), "pixels": int(n),
            "filters": float(ef[:, b].sum() / n) if n else None,
            "threshold": float(et[:, b].sum() / n) if n else None,
            "column": b,
        })  # fmt: skip
    return out


def _velocity_parts(seeds: Mapping[int, dict], b: dict) -> list[Part]:
    """S10's parts in one object size × speed bin: the filters' velocity error minus the error
    of reporting no motion (the objects' own speed: the absolute reading, "faithful" at the
    least), and minus the plain threshold's (px/frame, t over the seeds plus the paired
    bootstrap). A bin whose objects are in fewer than ``FLOORS["pairs"]`` test pairs is
    inconclusive: a wide range of sizes and speeds is not shown where it was not measured."""
    col = b["column"]
    size = f"size {100 * b['size'][0]:g}–{100 * b['size'][1]:g} % of the image"
    speed = f"speed {b['speed'][0]:g}–{b['speed'][1]:g} px" if b["speed"][1] < 999 else (
        f"speed ≥ {b['speed'][0]:g} px")  # fmt: skip
    where = f"{size}, {speed}"
    if b["pairs"] < FLOORS["pairs"]:
        missing = Part(f"velocity error, {where}", None, 0.0, "<=",
                       floor=f"objects in {b['pairs']} test pairs, below the floor of "
                       f"{FLOORS['pairs']:g}: not measured")  # fmt: skip
        missing.verdict = INCONCLUSIVE
        return [missing]
    columns = {}
    for s, r in sorted(seeds.items()):
        p = r["objects"]["pairs"]
        columns[s] = {
            "pix": np.asarray(p["filters"]["pixels"], dtype=float)[:, col],
            "filters": np.asarray(p["filters"]["err"], dtype=float)[:, col],
            "threshold": np.asarray(p["threshold"]["err"], dtype=float)[:, col],
        }
        if "speed" in p:
            columns[s]["no motion"] = np.asarray(p["speed"], dtype=float)[:, col]
    parts = []
    for other in ("no motion", "threshold"):
        if not all(other in c for c in columns.values()):
            continue
        vals, ses = [], []
        for s, c in columns.items():
            vals.append(float((c["filters"].sum() - c[other].sum()) / c["pix"].sum()))

            def diff(i: np.ndarray, c: dict = c, other: str = other) -> np.ndarray:
                return (c["filters"][i].sum(1) - c[other][i].sum(1)) / c["pix"][i].sum(1)

            ses.append(bootstrap_se(diff, len(c["pix"]), seed=s))
        means = {k: float(np.mean([c[k].sum() / c["pix"].sum() for c in columns.values()]))
                 for k in ("filters", other)}  # fmt: skip
        note = (
            f"filters {fmt(means['filters'], 3)} px, {other} {fmt(means[other], 3)} px (seed "
            f"means); {b['pixels']} object pixels in {b['pairs']} pairs"
        )
        parts.append(Part(f"velocity error, filters − {other} (px), {where}",
                          interval(vals, ses), 0.0, "<=", note=note, strict=True))  # fmt: skip
    return parts


def _grid_edges(seeds: Mapping[int, dict]) -> list[str]:
    """The seeds' filter constants chosen at the edge of their grid (a larger value might have
    done better on validation): "seed s name value" each."""
    edge = []
    for s, r in sorted(seeds.items()):
        fc = r["objects"].get("filters_choice") or {}
        grid = [tuple(float(x) for x in k.split(",")) for k in fc.get("iou", {})]
        for i, name in enumerate(("theta_d", "theta_p")):
            values = [g[i] for g in grid]
            if values and float(fc[name]) in (min(values), max(values)):
                edge.append(f"seed {s} {name} {fc[name]:g}")
    return edge


def _curve(seeds: Mapping[int, dict]) -> list[tuple[float, float]]:
    """The filters' validation curve along θ_d: at each θ_d of the grid, the largest mask IoU
    over θ_p, averaged over the seeds."""
    by: dict[float, list[float]] = {}
    for r in seeds.values():
        best: dict[float, float] = {}
        for key, iou in ((r["objects"].get("filters_choice") or {}).get("iou") or {}).items():
            d = float(key.split(",")[0])
            best[d] = max(best.get(d, -math.inf), float(iou))
        for d, v in best.items():
            by.setdefault(d, []).append(v)
    return [(d, float(np.mean(v))) for d, v in sorted(by.items())]


def object_sentences(settled: Settled) -> list[Judged]:
    """S9 and S10 on the exact-flow Table-2-sized models' object masks and velocities (every
    seed, per-pair counts: t over the seeds plus the paired bootstrap). Beside S10, its verdict
    under the rule stated before the strict one (an interval on its bound holds)."""
    j9, j10 = Judged(SENTENCES["S9"]), Judged(SENTENCES["S10"])
    seeds = {s: r for s, r in (settled.seeds.get("exact") or {}).items() if r.get("objects")}
    if not seeds:
        return [j9, j10]
    j9.parts += [_mask_part(seeds, "iou", "mask IoU, filters − threshold"),
                 _mask_part(seeds, "precision", "precision, filters − threshold")]  # fmt: skip
    bins, before = velocity_bins(seeds[min(seeds)]), None
    if len(seeds) < MIN_SEEDS:
        label = "velocity error, filters − threshold (px), every size × speed bin"
        j10.parts.append(Part(label, None, 0.0, "<=", floor=few_seeds(len(seeds))))
    else:
        j10.parts += [p for b in bins for p in _velocity_parts(seeds, b)]
        j10.close()
        parts = [replace(p, strict=False) if p.strict else p for p in j10.parts]
        before = Judged(j10.sentence, parts).close()
    found = {"n": len(seeds), "edges": _grid_edges(seeds), "curve": _curve(seeds),
             "world": (seeds[min(seeds)].get("object_set") or {}).get("world")}  # fmt: skip
    j9.beside = paragraph("beside/s9.md.j2", **found)
    j10.beside = paragraph("beside/s10.md.j2", **found, bins=bins, floor=int(FLOORS["pairs"]),
                           verdict=j10.verdict, before=before, changed=[
                               (p, q) for p, q in zip(j10.parts, before.parts, strict=True)
                               if p.verdict != q.verdict] if before else [])  # fmt: skip
    return [j9, j10]
