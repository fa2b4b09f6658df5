"""The pose pairs evo's RPE compares, and the options that choose them (``--delta``,
``--delta_unit``, ``--all_pairs``, ``--delta_tol``, ``--pairs_from_reference``) with evo's pose
relation (``-r``). numpy only: ``mfg-eval-poses`` checks them before torch is imported.

* in frames: ``(0, Δ), (Δ, 2Δ), …`` (every ``(i, i + Δ)`` with ``all_pairs``);
* in metres, along a path of positions: the next pose once the path since the last one reaches
  Δ (with ``all_pairs``: for every ``i`` the pose whose path distance from ``i`` is nearest Δ,
  kept within ``delta_tol · Δ``), as evo's ``id_pairs_from_delta`` pairs them.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

__all__ = ["POSE_RELATIONS", "RpeOptions", "rpe_pairs"]

#: evo's pose relations (``-r``) → the unit of their errors (``m`` in pose units).
POSE_RELATIONS: dict[str, str] = {
    "trans_part": "m",
    "rot_part": "1",
    "angle_rad": "rad",
    "angle_deg": "deg",
    "full": "1",
    "point_distance": "m",
}


@dataclass(frozen=True)
class RpeOptions:
    """Which pose pairs the RPE compares, and how (evo's flags).

    Attributes:
        delta: the gap Δ: frames (a whole number >= 1) or metres (> 0).
        delta_unit: ``"f"`` (frames) or ``"m"`` (metres of path).
        all_pairs: every pose starts a pair (overlapping pairs) instead of consecutive ones.
        delta_tol: with ``all_pairs`` in metres, the accepted relative deviation from Δ.
        pairs_from_reference: in metres, measure the path on the ground truth, not the estimate.
        pose_relation: evo's ``-r`` for the APE and RPE statistics (:data:`POSE_RELATIONS`).
    """

    delta: float = 1
    delta_unit: str = "f"
    all_pairs: bool = False
    delta_tol: float = 0.1
    pairs_from_reference: bool = False
    pose_relation: str = "trans_part"

    def __post_init__(self) -> None:
        if self.delta_unit not in ("f", "m"):
            raise ValueError(f"--delta_unit must be f (frames) or m (metres): {self.delta_unit}")
        if not (self.delta > 0 and math.isfinite(self.delta)):
            raise ValueError(f"--delta must be a finite gap > 0, got {self.delta:g}")
        if self.delta_unit == "f" and (self.delta < 1 or not float(self.delta).is_integer()):
            raise ValueError(f"--delta must be a whole number of frames >= 1, got {self.delta:g}")
        if not (self.delta_tol >= 0 and math.isfinite(self.delta_tol)):
            raise ValueError(f"--delta_tol must be a finite fraction >= 0, got {self.delta_tol:g}")
        if self.pose_relation not in POSE_RELATIONS:
            raise ValueError(f"pose relation must be one of {', '.join(POSE_RELATIONS)}")

    @property
    def frames(self) -> int:
        """Δ in frames (the gap needed between the first and last matched pose)."""
        return int(self.delta) if self.delta_unit == "f" else 1


def rpe_pairs(positions: np.ndarray, options: RpeOptions) -> tuple[np.ndarray, np.ndarray]:
    """The pose pairs of the RPE (module docstring; evo's ``id_pairs_from_delta``).

    Args:
        positions: ``(N, 3)`` positions the path is measured on (pose units); only their count
            matters for a Δ in frames.
        options: Δ, its unit and the pairing.

    Returns:
        ``(first, second)``: ``(K,)`` int64 row indices each, ``first < second``.
    """
    n = len(positions)
    if options.delta_unit == "f":
        d = int(options.delta)
        first = np.arange(0, max(n - d, 0)) if options.all_pairs else np.arange(0, n, d)[:-1]
        first = first[first + d < n]
        return first.astype(np.int64), (first + d).astype(np.int64)
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    path = np.concatenate([[0.0], np.cumsum(steps)])
    pairs: list[tuple[int, int]] = []
    if options.all_pairs:
        tol = options.delta * options.delta_tol
        for i in range(n - 1):
            ahead = path[i + 1 :] - path[i]
            k = int(np.argmin(np.abs(ahead - options.delta)))
            if abs(ahead[k] - options.delta) <= tol:
                pairs.append((i, i + 1 + k))
    else:
        ids, run = [0], 0.0
        for i in range(1, n):
            run += float(steps[i - 1])  # the same sums in the same order as evo's loop
            if run >= options.delta:
                ids.append(i)
                run = 0.0
        pairs = list(itertools.pairwise(ids))
    out = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    return out[:, 0], out[:, 1]
