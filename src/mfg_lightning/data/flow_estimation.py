"""Optical flow for datasets that ship none (KITTI odometry): an estimator and its disk cache.

The estimator is OpenCV's Dense Inverse Search (DIS), installed from the package registries with
``opencv-python-headless``; :class:`FlowCache` stores what it computed once so that later epochs
and runs read it back (atomic writes: concurrent runs sharing a cache never see half a file).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mfg_lightning.atomic import atomic_write_bytes

__all__ = ["DIS_PRESETS", "DISFlowEstimator", "FlowCache"]

DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
# dataset.dis_params keys → DISOpticalFlow setters (applied after the preset).
_DIS_SETTERS = {
    "finest_scale": "setFinestScale",
    "patch_size": "setPatchSize",
    "patch_stride": "setPatchStride",
    "grad_descent_iterations": "setGradientDescentIterations",
    "variational_refinement_iterations": "setVariationalRefinementIterations",
    "variational_refinement_alpha": "setVariationalRefinementAlpha",
    "variational_refinement_delta": "setVariationalRefinementDelta",
    "variational_refinement_gamma": "setVariationalRefinementGamma",
    "use_mean_normalization": "setUseMeanNormalization",
    "use_spatial_propagation": "setUseSpatialPropagation",
}


class DISFlowEstimator:
    """OpenCV's Dense Inverse Search optical flow.

    Args:
        preset: ``"ultrafast"``, ``"fast"`` or ``"medium"``.
        params: overrides applied after the preset (keys of ``_DIS_SETTERS``, e.g.
            ``{"variational_refinement_iterations": 10}``).
    """

    name = "dis"

    def __init__(self, preset: str = "medium", params: dict[str, Any] | None = None) -> None:
        if preset not in DIS_PRESETS:
            raise ValueError(
                f"dataset.dis_preset must be one of {sorted(DIS_PRESETS)}, got {preset!r}"
            )
        params = dict(params or {})
        unknown = sorted(set(params) - set(_DIS_SETTERS))
        if unknown:
            raise ValueError(f"unknown dataset.dis_params {unknown}; known: {sorted(_DIS_SETTERS)}")
        self.preset = preset
        self.params = params
        self._dis: Any = None

    def key(self) -> dict[str, Any]:
        """Everything about the estimator that changes its output (for the cache key)."""
        return {
            "estimator": self.name,
            "preset": self.preset,
            "params": {k: self.params[k] for k in sorted(self.params)},
            "opencv": cv2.__version__,
        }

    def __call__(self, gray0: np.ndarray, gray1: np.ndarray) -> np.ndarray:
        """Flow from ``gray0`` to ``gray1`` (``(H, W)`` uint8 each): ``(H, W, 2)`` float32 pixels
        with ``gray0(x) ≈ gray1(x + flow(x))``."""
        if self._dis is None:
            dis = cv2.DISOpticalFlow_create(DIS_PRESETS[self.preset])
            for name, value in self.params.items():
                getattr(dis, _DIS_SETTERS[name])(value)
            self._dis = dis
        return self._dis.calc(gray0, gray1, None)

    def __getstate__(self) -> dict[str, Any]:
        # cv2 objects do not pickle; each DataLoader worker builds its own.
        return {**self.__dict__, "_dis": None}


@dataclass(frozen=True)
class FlowCache:
    """On-disk cache of computed flow (and resized RGB) at the model's input size.

    ``<root>/<seq>@<H>x<W>/<src:06d>_<tgt:06d>.npy`` holds ``(h, w, 2)`` float32 flow (pixels of
    the ``h × w`` input size) computed on ``H × W`` images; ``<root>/<seq>_rgb/<frame:06d>.npy``
    the ``(h, w, 3)`` uint8 source image at the input size, so that a cached epoch decodes no
    PNG at all. ``root`` is ``<cache_dir>/kitti_flow/<key>`` and ``<root>/meta.json`` records
    what the key stands for.
    """

    root: Path

    @classmethod
    def create(cls, cache_dir: str | os.PathLike, key: dict[str, Any]) -> FlowCache:
        text = json.dumps(key, sort_keys=True)
        digest = hashlib.sha256(text.encode()).hexdigest()[:16]
        root = Path(cache_dir).expanduser() / "kitti_flow" / digest
        meta = root / "meta.json"
        if not meta.exists():
            atomic_write_bytes(meta, json.dumps(key, sort_keys=True, indent=2).encode())
        return cls(root)

    def path(self, seq: str, compute_hw: tuple[int, int], src: int, tgt: int) -> Path:
        return self.root / f"{seq}@{compute_hw[0]}x{compute_hw[1]}" / f"{src:06d}_{tgt:06d}.npy"

    def rgb_path(self, seq: str, frame: int) -> Path:
        return self.root / f"{seq}_rgb" / f"{frame:06d}.npy"

    def load(self, path: Path, shape: tuple[int, ...], dtype: type) -> np.ndarray | None:
        """The cached array, or None if absent or unusable (then it is recomputed)."""
        try:
            array = np.load(path, allow_pickle=False)
        except (FileNotFoundError, ValueError, OSError, EOFError):
            return None
        if array.shape != shape or array.dtype != dtype:
            return None
        return array

    def store(self, path: Path, array: np.ndarray) -> None:
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
        atomic_write_bytes(path, buf.getvalue())
