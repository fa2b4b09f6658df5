"""KITTI odometry drift (Geiger et al. 2012, the KITTI odometry devkit's ``evaluate_odometry``).

Definition (``docs/protocols.md``, "KITTI odometry drift", as computed by the devkit's
``calcSequenceErrors``), for ground-truth poses ``Q`` and estimated poses ``P`` of one sequence:

* ``dist[k]``: the ground-truth path length from frame 0 to frame k (sum of the distances between
  consecutive positions);
* for every first frame ``f = 0, 10, 20, …`` and every length ``len = 100, 200, …, 800`` m, the last
  frame ``l`` is the first frame with ``dist[l] > dist[f] + len``; the segment is skipped when the
  sequence ends before;
* ``E = (P_f^-1 · P_l)^-1 · (Q_f^-1 · Q_l)`` (note the order: the inverse estimate first), the
  segment's translational error ``‖translation(E)‖ / len`` and rotational error
  ``angle(E) / len`` with ``angle = arccos(clip((tr R − 1) / 2, −1, 1))``;
* the result is the mean over all segments (of all sequences pooled, as the devkit's ``saveStats``):
  ``t_err`` in % (×100) and ``r_err`` in degrees per 100 m (×180/π×100).

Differences from the C++ devkit, on purpose: float64 instead of float32 throughout (the devkit's
float32 path length can move a segment's last frame by one at exact ties), and rotation blocks
projected onto SO(3) first (:func:`mfg_lightning.trajectory.trajectories.evaluation_poses`).
Neither changes a
leaderboard-scale number. With no complete segment (a path shorter than 100 m) the drift is
undefined and NaN is returned.

Alignment (``align``, as kitti-odom-eval's ``--align``): the devkit aligns nothing, so by default
(``none``) a monocular method's poses must be in metres. With ``se3``, ``sim3`` or ``scale`` the
estimate is first aligned to the ground truth (:mod:`mfg_lightning.metrics.alignment`, optionally
fitted on the first ``n_to_align`` poses), then the segments are scored as above. Segment errors
compare relative poses, so a rigid alignment leaves them unchanged (``se3`` equals ``none``);
the scale of ``sim3`` and ``scale`` multiplies every estimated relative translation.
:func:`kitti_drift_by_length` gives the devkit's per-length averages (its ``tl``/``rl`` plots).

An estimate with poses for some frames only (``frames``: a late start, an early end, holes; or the
poses matched by timestamp) is scored as kitti-odom-eval's ``calc_sequence_errors`` scores it: the
path length ``dist`` and the segments' first frames ``0, 10, 20, …`` are those of the whole ground
truth (``reference``), and a segment counts when the estimate has a pose at both its first and
its last frame. ``project=False`` keeps the rotation blocks as written and inverts with general
matrix inverses (kitti-odom-eval's arithmetic).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from mfg_lightning.core import geometry
from mfg_lightning.metrics.alignment import align_trajectory, check_align_options
from mfg_lightning.metrics.stats import MetricValues, cat_state, summary
from mfg_lightning.trajectory.trajectories import (
    check_sequence_pair,
    evaluation_poses,
    relative_poses,
)

__all__ = [
    "DRIFT_NAMES",
    "KITTI_SEGMENT_LENGTHS",
    "KITTI_STEP",
    "KittiDrift",
    "kitti_drift",
    "kitti_drift_by_length",
    "kitti_drift_from_segments",
    "kitti_segment_errors",
]

#: Segment lengths of the devkit in metres.
KITTI_SEGMENT_LENGTHS: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
#: Frames between segment starts in the devkit ("every second" at 10 Hz).
KITTI_STEP = 10
#: The published names of the drift: translational error in %, rotational error in deg / 100 m.
DRIFT_NAMES: tuple[str, ...] = ("drift_t_err", "drift_r_err")


def kitti_segment_errors(
    pred: Tensor,
    target: Tensor,
    lengths: Sequence[float] = KITTI_SEGMENT_LENGTHS,
    step: int = KITTI_STEP,
    align: str = "none",
    n_to_align: int | None = None,
    *,
    frames: Tensor | None = None,
    reference: Tensor | None = None,
    project: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-segment errors of one sequence, as the devkit's ``calcSequenceErrors``.

    Args:
        pred: ``(M, 4, 4)`` estimated camera-to-world poses (metres), in frame order.
        target: ``(M, 4, 4)`` ground-truth camera-to-world poses of the same frames (metres).
        lengths: segment lengths of ground-truth path in metres.
        step: frames between two segment starts.
        align: alignment of the estimate first (module docstring): ``"none"`` (the devkit),
            ``"se3"``, ``"sim3"``, ``"scale"`` or ``"scale_7dof"``.
        n_to_align: fit the alignment on the first N poses (``None``: all).
        frames: ``(M,)`` non-decreasing indices of the rows' frames in ``reference`` (``None``: the
            rows are the frames ``0 … M − 1`` and ``reference`` is ``target``).
        reference: ``(N, 4, 4)`` the whole ground truth, whose path length places the segments
            (needed with ``frames``).
        project: rotation blocks onto SO(3) first (default); ``False``: kitti-odom-eval's
            arithmetic.

    Returns:
        ``(t_err, r_err, length)``, ``(S,)`` float64 each, for the S complete segments ordered by
        first frame, then length: translational error per metre (a fraction), rotational error in
        radians per metre, and the segment's nominal length in metres.
    """
    check_sequence_pair(pred, target)
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    check_align_options(align, n_to_align)
    if align == "none":
        P = evaluation_poses(pred, project)
        Q = evaluation_poses(target, project).to(P.device)
    else:
        aligned = align_trajectory(pred, target, align, n_to_align, project=project)
        P, Q = aligned.pred, aligned.target
    path, rows = Q, None
    if frames is not None:
        if reference is None or tuple(frames.shape) != (pred.shape[0],):
            raise ValueError("frames must be (M,) for M poses, with the whole ground truth")
        path = reference.detach().to(Q.device, torch.float64)
        rows = _rows_of_frames(frames.to(Q.device), path.shape[0])
    first, last, seg = _segments(path[:, :3, 3], lengths, step)
    if rows is not None:
        # A segment needs an estimated pose at its first and at its last frame.
        keep = (rows[first] >= 0) & (rows[last] >= 0)
        first, last, seg = rows[first[keep]], rows[last[keep]], seg[keep]
    delta_est = relative_poses(P[first], P[last], project)
    delta_gt = relative_poses(Q[first], Q[last], project)
    error = relative_poses(delta_est, delta_gt, project)
    t_err = error[:, :3, 3].norm(dim=-1) / seg
    r_err = geometry.rotation_angle(error[:, :3, :3]) / seg
    return t_err, r_err, seg


def _segments(
    positions: Tensor, lengths: Sequence[float], step: int
) -> tuple[Tensor, Tensor, Tensor]:
    """The devkit's complete segments of a ground-truth path.

    Args:
        positions: ``(N, 3)`` ground-truth positions (metres), every frame in order.
        lengths, step: segment lengths (m) and frames between segment starts.

    Returns:
        ``(first, last, length)``, ``(S,)`` each: the first and last frame of every complete
        segment (ordered by first frame, then length) and its nominal length (float64, m).
    """
    n = positions.shape[0]
    seg = torch.as_tensor(lengths, dtype=torch.float64, device=positions.device)
    steps = (positions[1:] - positions[:-1]).norm(dim=-1)
    dist = torch.cat([steps.new_zeros(1), steps.cumsum(0)])
    first = torch.arange(0, n, step, device=positions.device)
    # dist is non-decreasing, so the first frame with dist > dist[f] + len is a sorted search;
    # frames before f have dist <= dist[f] and are never returned.
    last = torch.searchsorted(dist, dist[first][:, None] + seg[None, :], right=True)
    complete = last < n
    first = first[:, None].expand_as(last)[complete]
    return first, last[complete], seg[None, :].expand(complete.shape)[complete]


def _rows_of_frames(frames: Tensor, n: int) -> Tensor:
    """``(n,)`` long: ``rows[f]`` the first row whose frame is ``f``, −1 where no row is.

    Args:
        frames: ``(M,)`` non-decreasing frame indices in ``[0, n)`` (timestamp association may
            match one frame twice; its first row is kept).
        n: the frames of the reference.
    """
    frames = frames.long()
    if frames.numel() and (int(frames.min()) < 0 or int(frames.max()) >= n):
        raise ValueError(f"frames must index the {n} poses of the reference")
    if bool((torch.diff(frames) < 0).any()):
        raise ValueError("frames must be in increasing order")
    first = torch.ones_like(frames, dtype=torch.bool)
    first[1:] = frames[1:] != frames[:-1]
    rows = torch.full((n,), -1, dtype=torch.long, device=frames.device)
    rows[frames[first]] = torch.arange(frames.shape[0], device=frames.device)[first]
    return rows


def _drift(t_err: Tensor, r_err: Tensor) -> MetricValues:
    """:data:`DRIFT_NAMES` from per-segment errors: the means in % and deg / 100 m (NaN: none)."""
    return MetricValues(
        drift_t_err=summary(t_err)["mean"] * 100.0,
        drift_r_err=summary(r_err)["mean"] * (180.0 / math.pi) * 100.0,
    )


def kitti_drift_from_segments(t_err: Tensor, r_err: Tensor) -> dict[str, Tensor]:
    """The devkit's overall numbers from per-segment errors (of one or several sequences).

    Args:
        t_err, r_err: ``(S,)`` as returned by :func:`kitti_segment_errors` (per metre).

    Returns:
        ``{"t_err", "r_err"}``: mean translational error in %, mean rotational error in degrees
        per 100 m (float64 scalars; NaN when ``S == 0``). The devkit's own short names, kept
        for ``mfg-eval-poses``, which prefixes them itself; :class:`KittiDrift`,
        :func:`kitti_drift` and :func:`kitti_drift_by_length` report the published
        :data:`DRIFT_NAMES` of the same values.
    """
    drift = _drift(t_err, r_err)
    return {"t_err": drift["drift_t_err"], "r_err": drift["drift_r_err"]}


def kitti_drift_by_length(
    t_err: Tensor, r_err: Tensor, length: Tensor
) -> dict[float, dict[str, Tensor]]:
    """Mean drift per segment length (the devkit's per-length plots, kitti-odom-eval's
    ``compute_segment_error``).

    Args:
        t_err, r_err, length: ``(S,)`` as returned by :func:`kitti_segment_errors` (of one or
            several sequences).

    Returns:
        ``{length (m): {"drift_t_err" (%), "drift_r_err" (deg/100 m), "count"}}`` for every length
        that has at least one segment, in increasing length (``"t_err"``, ``"r_err"`` still read).
    """
    out: dict[float, dict[str, Tensor]] = {}
    for value in torch.unique(length).tolist():
        keep = length == value
        out[float(value)] = MetricValues(**_drift(t_err[keep], r_err[keep]), count=keep.sum())
    return out


def kitti_drift(pred: Tensor, target: Tensor, **options: Any) -> MetricValues:
    """KITTI drift of one sequence: the functional twin of :class:`KittiDrift`.

    Args:
        pred, target: ``(N, 4, 4)`` estimated and ground-truth camera-to-world poses (metres).
        options: ``lengths``, ``step`` (the devkit's segment lengths in m and start spacing in
            frames), ``align``, ``n_to_align`` (alignment of the estimate first) of
            :func:`kitti_segment_errors`, with its defaults.

    Returns:
        ``{"drift_t_err", "drift_r_err"}`` (:data:`DRIFT_NAMES`): float64 scalars, the mean
        translational error in % of the distance travelled and the mean rotational error in
        degrees per 100 m; NaN without segments. ``"t_err"``, ``"r_err"`` (the names the function
        returned before it took the logged ones) still read.
    """
    t_err, r_err, _ = kitti_segment_errors(pred, target, **options)
    return _drift(t_err, r_err)


class KittiDrift(Metric):
    """KITTI odometry drift accumulated over sequences (Geiger et al. 2012), DDP-safe.

    Each ``update`` takes one whole sequence (segments are up to 800 m long, so a sequence cannot
    be split). Per-segment errors are stored in list states reduced by concatenation; ``compute``
    averages over all segments of all sequences, as the devkit does for its overall numbers.

    Args:
        lengths, step: the devkit's segment lengths (m) and start spacing (frames).
        align, n_to_align: alignment of each sequence's estimate first (module docstring).
        kwargs: passed to :class:`torchmetrics.Metric`.

    ``compute()`` returns ``{"drift_t_err", "drift_r_err"}`` (% and deg/100 m; NaN without
    segments).
    """

    names = DRIFT_NAMES
    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(
        self,
        lengths: Sequence[float] = KITTI_SEGMENT_LENGTHS,
        step: int = KITTI_STEP,
        align: str = "none",
        n_to_align: int | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        check_align_options(align, n_to_align)
        self.lengths = tuple(float(x) for x in lengths)
        self.step = step
        self.align = align
        self.n_to_align = n_to_align
        self.add_state("t_values", default=[], dist_reduce_fx="cat")
        self.add_state("r_values", default=[], dist_reduce_fx="cat")

    def update(self, pred: Tensor, target: Tensor) -> None:
        """Add the segments of one sequence.

        Args:
            pred: ``(N, 4, 4)`` estimated camera-to-world poses (metres), in frame order.
            target: ``(N, 4, 4)`` ground-truth camera-to-world poses (metres), in frame order.
        """
        t_err, r_err, _ = kitti_segment_errors(
            pred, target, self.lengths, self.step, self.align, self.n_to_align
        )
        self.t_values.append(t_err)
        self.r_values.append(r_err)

    def compute(self) -> MetricValues:
        """``{"drift_t_err", "drift_r_err"}`` over every segment seen."""
        return _drift(cat_state(self.t_values), cat_state(self.r_values))
