"""A flow estimate's quality pooled pixel by pixel over a split, per named set of pixels: the mean
end-point error (px) and KITTI's Fl outlier rate (%).

Two forms of the same sums: per pair of rendered frames in numpy, per region of the renderer's
region map (:func:`flow_quality`, what the ``flow=dis`` cache keeps beside each estimate,
:func:`pair_stats`), pooled over a split's pairs (:func:`pooled_quality`,
:func:`pooled_quality_by_offset`, :func:`summarize_quality`); and as a torchmetrics ``Metric``
(:class:`PooledFlowQuality`) whose sums are added up across processes where Lightning and
torchmetrics reduce (``compute``).

Scored as KITTI 2015 scores flow, on two sets of pixels (:data:`QUALITY_SETS`): ``noc``, the
non-occluded pixels (the exact flow known, the point visible in the second frame and landing
inside it) and ``all``, every pixel whose exact flow is known, occluded and out-of-frame ones
included (their flow is known exactly; only the second image cannot show where they went, so an
estimate from the two images has to guess it). The renderer marks each pixel
(:func:`mfg_lightning.scene.render.exact_flow`'s ``"out_of_frame"`` and ``"occluded"``); a
rendered pair keeps the marks as one code per pixel (:func:`visibility_codes`)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torchmetrics import Metric

__all__ = [
    "OCCLUDED",
    "OUT_OF_FRAME",
    "PAIR_STATS_SIZE",
    "QUALITY_REGIONS",
    "QUALITY_SETS",
    "UNKNOWN",
    "VISIBLE",
    "PooledFlowQuality",
    "flow_quality",
    "pair_stats",
    "pooled_quality",
    "pooled_quality_by_offset",
    "quality_line",
    "region_codes",
    "summarize_noc_all",
    "summarize_quality",
    "visibility_codes",
]

#: The regions flow quality is reported for (the renderer's region map), then all pixels.
QUALITY_REGIONS = ("road", "structure", "moving", "far", "all")
#: The sets of pixels every region is scored on, in the order of :func:`flow_quality`'s first
#: axis: ``noc`` (visible in the second frame and inside it) and ``all`` (flow known).
QUALITY_SETS = ("noc", "all")

#: A pixel's visibility code (uint8, :func:`visibility_codes`): its exact flow is unknown (a
#: point behind the second camera; in neither set).
UNKNOWN = 0
#: ... the point is visible in the second frame (``noc`` and ``all``).
VISIBLE = 1
#: ... it lands inside the second frame but is hidden there (``all`` only).
OCCLUDED = 2
#: ... it lands outside the second frame (``all`` only).
OUT_OF_FRAME = 3


class PooledFlowQuality(Metric):
    """Per name of ``names``: the sum of the end-point errors (px), the number of Fl outliers and
    the number of pixels counted, kept as sums (float64) so that batches and processes pool by
    addition (``dist_reduce_fx="sum"``: every pixel counted once, whichever process scored it).

    ``update`` reads nothing back from the device; ``compute`` gives, per name with at least one
    pixel, ``(mean EPE px, Fl outliers %)``.

    An Fl outlier (KITTI 2015) is a pixel whose end-point error exceeds 3 px and 5 % of the exact
    flow's magnitude; the caller computes it (``outlier``) beside the errors.

    Args:
        names: the sets of pixels, in a fixed order (the same on every process: a process may
            see no pixel of some set).
    """

    full_state_update = False

    def __init__(self, names: Sequence[str], **kwargs: object) -> None:
        super().__init__(**kwargs)
        self.names = tuple(names)
        self._index = {name: i for i, name in enumerate(self.names)}
        self.add_state(
            "sums",
            default=torch.zeros(len(self.names), 3, dtype=torch.float64),
            dist_reduce_fx="sum",
        )

    def update(self, epe: Tensor, outlier: Tensor, masks: Mapping[str, Tensor]) -> None:
        """Add a batch's pixels.

        Args:
            epe: ``(B, H, W)`` end-point errors (px).
            outlier: ``(B, H, W)`` bool, the Fl outliers.
            masks: ``(B, H, W)`` bool per name, the pixels of that set (names not in ``names``
                are left out).
        """
        rows, index = [], []
        for name, mask in masks.items():
            if name in self._index:
                rows.append(torch.stack((epe[mask].sum(), outlier[mask].sum().float(),
                                         mask.sum().float())))  # fmt: skip
                index.append(self._index[name])
        if rows:
            at = torch.tensor(index, device=self.sums.device)
            self.sums = self.sums.index_add(0, at, torch.stack(rows).to(self.sums))

    def compute(self) -> dict[str, tuple[float, float]]:
        """``{name: (mean EPE px, Fl outliers %)}`` for every name with a pixel (one host read)."""
        out = {}
        for name, (epe, outliers, n) in zip(self.names, self.sums.tolist(), strict=True):
            if n > 0:
                out[name] = (epe / n, 100.0 * outliers / n)
        return out


# -- per pair of rendered frames, pooled over a split (numpy) ---------------------------------


def region_codes() -> list[tuple[str, int | None]]:
    """``(name, code)`` of every :data:`QUALITY_REGIONS` entry in the renderer's region map
    (``None``: all pixels)."""
    # (the renderer imported on first use, so that flow=exact never loads it)
    from mfg_lightning.scene import render

    codes = {
        "road": render.REGION_ROAD,
        "structure": render.REGION_STRUCTURE,
        "moving": render.REGION_MOVING,
        "far": render.REGION_FAR,
    }
    return [(name, codes.get(name)) for name in QUALITY_REGIONS]


def visibility_codes(
    valid: np.ndarray, out_of_frame: np.ndarray, occluded: np.ndarray
) -> np.ndarray:
    """One visibility code per pixel from the renderer's masks
    (:func:`mfg_lightning.scene.render.exact_flow`).

    Args:
        valid: ``(H, W)`` bool, the exact flow is known.
        out_of_frame: ``(H, W)`` bool, it lands outside the second frame.
        occluded: ``(H, W)`` bool, it lands inside but the point is hidden there.

    Returns:
        ``(H, W)`` uint8: :data:`UNKNOWN` where not ``valid``, else :data:`OUT_OF_FRAME`,
        :data:`OCCLUDED` or :data:`VISIBLE`.
    """
    valid, out_of_frame, occluded = (np.asarray(a, bool) for a in (valid, out_of_frame, occluded))
    hidden = np.where(out_of_frame, OUT_OF_FRAME, np.where(occluded, OCCLUDED, VISIBLE))
    return np.where(valid, hidden, UNKNOWN).astype(np.uint8)


def flow_quality(
    estimated: np.ndarray,
    exact: np.ndarray,
    valid: np.ndarray,
    region: np.ndarray,
    noc: np.ndarray,
) -> np.ndarray:
    """End-point error and KITTI's Fl outliers of an estimated flow against the exact one, on
    the non-occluded pixels and on all pixels (:data:`QUALITY_SETS`).

    A pixel is an Fl outlier when its end-point error exceeds 3 px *and* 5 % of the exact flow's
    magnitude (the KITTI 2015 flow benchmark's definition).

    Args:
        estimated, exact: ``(H, W, 2)`` pixels (at the image size the flow was estimated at).
        valid: ``(H, W)`` bool, the pixels that count (exact flow known, estimate finite): the
            ``all`` set.
        region: ``(H, W)`` the renderer's region code of every pixel.
        noc: ``(H, W)`` bool, the pixels visible in the second frame and inside it (a
            visibility code of :data:`VISIBLE`); the ``noc`` set is ``valid & noc``.

    Returns:
        ``(len(QUALITY_SETS), len(QUALITY_REGIONS), 3)`` float64: per set (``noc``, ``all``)
        and region, the sum of the end-point errors (pixels), the number of outliers and the
        number of pixels counted; sums, so that pairs pool by addition.
    """
    epe = np.linalg.norm(estimated.astype(np.float64) - exact, axis=2)
    outlier = (epe > 3.0) & (epe > 0.05 * np.linalg.norm(exact.astype(np.float64), axis=2))
    out = np.zeros((len(QUALITY_SETS), len(QUALITY_REGIONS), 3))
    sets = {"noc": valid & np.asarray(noc, bool), "all": valid}
    for s, name in enumerate(QUALITY_SETS):
        for r, (_, code) in enumerate(region_codes()):
            m = sets[name] if code is None else sets[name] & (region == code)
            out[s, r] = (epe[m].sum(), outlier[m].sum(), m.sum())
    return out


def summarize_quality(stats: np.ndarray) -> dict[str, dict[str, float | None]]:
    """Pooled ``{region: {"epe": px, "fl": %, "pixels": n}}`` from summed per-pair stats of one
    set of pixels (``(..., R, 3)``: pairs pooled pixel by pixel; None where a region had no
    pixel)."""
    total = stats.reshape(-1, len(QUALITY_REGIONS), 3).sum(axis=0)
    out: dict[str, dict[str, float | None]] = {}
    for name, (epe, outliers, n) in zip(QUALITY_REGIONS, total, strict=True):
        out[name] = {
            "epe": float(epe / n) if n else None,
            "fl": float(100.0 * outliers / n) if n else None,
            "pixels": float(n),
        }
    return out


def summarize_noc_all(stats: np.ndarray) -> dict[str, dict[str, dict[str, float | None]]]:
    """Both sets of summed stats (``(..., len(QUALITY_SETS), R, 3)``, :func:`flow_quality`'s
    sums of any number of pairs) pooled: ``{"regions": <all pixels>, "regions_noc": <noc>}``,
    each as :func:`summarize_quality` (``regions`` keeps its name from before the sets were
    split: it is what every report read)."""
    total = stats.reshape(-1, len(QUALITY_SETS), len(QUALITY_REGIONS), 3).sum(axis=0)
    return {
        "regions": summarize_quality(total[QUALITY_SETS.index("all")]),
        "regions_noc": summarize_quality(total[QUALITY_SETS.index("noc")]),
    }


#: The length of a pair's sums (:func:`pair_stats`): both sets' quality, then the occluded,
#: out-of-frame and non-finite estimated pixel counts.
PAIR_STATS_SIZE = len(QUALITY_SETS) * len(QUALITY_REGIONS) * 3 + 3


def pair_stats(
    quality: np.ndarray,
    nonfinite: int | np.integer,
    occluded: int | np.integer = 0,
    out_of_frame: int | np.integer = 0,
) -> np.ndarray:
    """A pair's quality sums as the ``flow=dis`` cache keeps them (``stats``):
    :func:`flow_quality`'s ``(2, R, 3)`` flattened, then the pair's occluded and out-of-frame
    pixel counts (exact flow known, not visible in the second frame) and its non-finite
    estimated pixel count; ``(PAIR_STATS_SIZE,)`` float64."""
    counts = [float(occluded), float(out_of_frame), float(nonfinite)]
    return np.concatenate([np.asarray(quality, np.float64).ravel(), counts])


def _split_pair(pair: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A pair's sums (:func:`pair_stats`) as ``((2, R, 3) quality, (3,) counts)``; refused (a
    cache of another layout) when the length is not :data:`PAIR_STATS_SIZE`."""
    if pair.shape != (PAIR_STATS_SIZE,):
        raise ValueError(
            f"a pair's quality sums have {PAIR_STATS_SIZE} entries, got shape {pair.shape} "
            "(written by an older version: remove that cache)"
        )
    quality = pair[:-3].reshape(len(QUALITY_SETS), len(QUALITY_REGIONS), 3)
    return quality, pair[-3:]


def pooled_quality(pairs: Iterable[np.ndarray]) -> dict[str, Any]:
    """The flow quality of a set of pairs, pooled pixel by pixel, and their pixel counts.

    Args:
        pairs: each pair's sums (:func:`pair_stats`, ``(PAIR_STATS_SIZE,)``).

    Returns:
        ``{"regions": <all pixels>, "regions_noc": <non-occluded pixels>}``
        (:func:`summarize_noc_all`) with ``"occluded_pixels"``, ``"out_of_frame_pixels"`` and
        ``"nonfinite_pixels"`` (totals over the pairs).
    """
    stats = np.zeros((len(QUALITY_SETS), len(QUALITY_REGIONS), 3))
    counts = np.zeros(3)
    for pair in pairs:
        quality, n = _split_pair(pair)
        stats += quality
        counts += n
    occluded, out_of_frame, nonfinite = (int(c) for c in counts)
    return {
        **summarize_noc_all(stats),
        "occluded_pixels": occluded,
        "out_of_frame_pixels": out_of_frame,
        "nonfinite_pixels": nonfinite,
    }


def pooled_quality_by_offset(pairs: Iterable[tuple[int, np.ndarray]]) -> dict[str, dict[str, Any]]:
    """The flow quality pooled per frame offset (target − source):
    ``{"-2": {"regions": ..., "regions_noc": ..., "pairs": n}, "-1": ..., "1": ..., "2": ...}``,
    offsets in increasing order (the estimate's error grows with the motion it has to find,
    which the offset scales).

    Args:
        pairs: ``(offset, sums)`` of each pair (:func:`pair_stats`, ``(PAIR_STATS_SIZE,)``).
    """
    stats: dict[int, np.ndarray] = {}
    counts: dict[int, int] = {}
    for off, pair in pairs:
        pooled = stats.setdefault(off, np.zeros((len(QUALITY_SETS), len(QUALITY_REGIONS), 3)))
        pooled += _split_pair(pair)[0]
        counts[off] = counts.get(off, 0) + 1
    return {str(o): {**summarize_noc_all(stats[o]), "pairs": counts[o]} for o in sorted(stats)}


def quality_line(regions: dict[str, dict[str, float | None]]) -> str:
    """``road EPE 1.23 px Fl 4.5 % · …`` for the log."""

    def one(name: str, q: dict[str, float | None]) -> str:
        if q["epe"] is None:
            return f"{name} –"
        return f"{name} EPE {q['epe']:.2f} px Fl {q['fl']:.1f} %"

    return " · ".join(one(k, v) for k, v in regions.items())
