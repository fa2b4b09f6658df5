"""evo's result archive: the ``.zip`` that ``evo_ape`` / ``evo_rpe --save_results`` write and
``evo_res`` reads, written by this project's own code (evo is not imported).

The layout (evo 1.x ``file_interface.save_res_file``; ``load_res_file`` needs the first two):

* ``info.json``: ``{"title", "ref_name", "est_name", "label"}``, ``label`` the metric and its
  unit as evo writes it, e.g. ``"APE (m)"``; ``evo_res`` names a result after ``est_name``;
* ``stats.json``: the statistics, ``{"max", "mean", "median", "min", "rmse", "sse", "std"}``;
* ``<name>.npy`` per array, in numpy's ``.npy`` format: ``error_array`` (the per-element errors)
  and, for timestamped estimates, ``timestamps`` and ``seconds_from_start`` (the axis
  ``evo_res`` plots against).

evo also stores the two trajectories (``<name>.tum`` / ``.kitti``) as a backup that ``evo_res``
does not read; they are left out.
"""

from __future__ import annotations

import io
import json
import math
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mfg_lightning.core.atomic import atomic_write_bytes

__all__ = ["result_archive_bytes", "write_result_archive"]


def result_archive_bytes(
    info: Mapping[str, str],
    stats: Mapping[str, float | None],
    arrays: Mapping[str, np.ndarray],
) -> bytes:
    """The archive's bytes (module docstring).

    Args:
        info: ``title``, ``ref_name``, ``est_name`` and ``label``.
        stats: statistic name → value; None (an empty set) is written as NaN, as evo would
            compute it.
        arrays: name → array, e.g. ``error_array`` ``(K,)`` float64.
    """
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("info.json", json.dumps(dict(info)))
        archive.writestr(
            "stats.json",
            json.dumps({k: math.nan if v is None else float(v) for k, v in stats.items()}),
        )
        for name, array in arrays.items():
            npy = io.BytesIO()
            np.save(npy, np.asarray(array))
            archive.writestr(f"{name}.npy", npy.getvalue())
    return buffer.getvalue()


def write_result_archive(
    path: str | Path,
    info: Mapping[str, str],
    stats: Mapping[str, float | None],
    arrays: Mapping[str, np.ndarray],
) -> Path:
    """Write :func:`result_archive_bytes` to ``path`` atomically; returns the path."""
    path = Path(path)
    atomic_write_bytes(path, result_archive_bytes(info, stats, arrays))
    return path
