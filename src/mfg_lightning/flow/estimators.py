"""Where a dataset's input flow comes from (the ``flow`` config group), the estimators, the cache.

The ``flow`` group (``conf/flow/``) picks the source of the flow that a dataset feeds the model;
:func:`parse_flow` turns its config into one of

* :class:`ExactFlow` (``flow=exact``): the exact reprojection flow of a synthetic scene with
  Gaussian noise and single-pixel outliers (the synthetic default);
* :class:`EstimatedFlow` (``flow=dis``, ``flow=deepflow``, ``tvl1``, ``pcaflow``, ``farneback``,
  ``sparse_to_dense``, ``rlof``, ``learned``): an estimator run on images (rendered synthetic
  frames or KITTI's real ones) at ``flow.height × flow.width``, resized to the model input with
  the vectors rescaled, cached; the KITTI default. An estimator is any class in
  :data:`ESTIMATORS` with the :class:`FlowEstimator` interface (each gets a
  ``conf/flow/<name>.yaml`` with ``source: <name>``);
* :class:`FlowFiles` (``flow=files``): the user's own flow files;
* :class:`GroundTruthFlow` (``flow=ground_truth``): the flow files a dataset ships as ground
  truth (Virtual KITTI's rendered flow, its only source and default).

Each dataset accepts the sources it can give and refuses the others naming ``flow.source``.

The DIS estimator is OpenCV's Dense Inverse Search; the others are OpenCV's contrib algorithms
(:class:`OpenCVFlowEstimator`), all from ``opencv-contrib-python-headless`` (the plain
``opencv-python-headless`` has DIS only; the two packages must not be installed together);
:class:`FlowCache` stores what was computed once so that later epochs
and runs read it back (atomic writes: concurrent runs sharing a cache never see half a file).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

import cv2
import numpy as np

from mfg_lightning.core.atomic import atomic_write_bytes
from mfg_lightning.flow.learned import LearnedFlowEstimator

__all__ = [
    "DIS_PRESETS",
    "ESTIMATORS",
    "DISFlowEstimator",
    "EstimatedFlow",
    "ExactFlow",
    "FlowCache",
    "FlowEstimator",
    "FlowFiles",
    "GroundTruthFlow",
    "OpenCVFlowEstimator",
    "flow_sources",
    "parse_flow",
]

DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
# flow.params keys → DISOpticalFlow setters (applied after the preset).
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


class FlowEstimator(Protocol):
    """What :class:`EstimatedFlow` needs of an estimator (DIS here; a learned one later).

    ``name`` is its ``flow.source``; ``key()`` every setting and version that changes its output
    (it goes into the cache key); ``prepare`` turns an ``(H, W, 3)`` uint8 RGB image into the
    estimator's input (done once per frame, then resized to the estimation size if needed:
    ``cv2.resize`` must accept it); ``__call__`` estimates the flow between two prepared images
    as ``(H, W, 2)`` float32 pixels with ``image0(x) ≈ image1(x + flow(x))``.
    """

    name: str

    def key(self) -> dict[str, Any]: ...

    def prepare(self, rgb: np.ndarray) -> np.ndarray: ...

    def __call__(self, image0: np.ndarray, image1: np.ndarray) -> np.ndarray: ...


class DISFlowEstimator:
    """OpenCV's Dense Inverse Search optical flow (``flow=dis``), on grey images.

    Args:
        preset: ``"ultrafast"``, ``"fast"`` or ``"medium"``.
        params: overrides applied after the preset (keys of ``_DIS_SETTERS``, e.g.
            ``{"variational_refinement_iterations": 10}``).
    """

    name = "dis"

    def __init__(self, preset: str = "medium", params: dict[str, Any] | None = None) -> None:
        if preset not in DIS_PRESETS:
            raise ValueError(f"flow.preset must be one of {sorted(DIS_PRESETS)}, got {preset!r}")
        params = dict(params or {})
        unknown = sorted(set(params) - set(_DIS_SETTERS))
        if unknown:
            raise ValueError(f"unknown flow.params {unknown}; known: {sorted(_DIS_SETTERS)}")
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

    def prepare(self, rgb: np.ndarray) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB → the ``(H, W)`` uint8 grey image DIS works on."""
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)

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


class OpenCVFlowEstimator:
    """One of OpenCV's dense optical-flow algorithms of its contrib modules (``cv2.optflow``,
    from the ``opencv-contrib-python-headless`` package), at its defaults.

    A subclass names the algorithm: :attr:`name` (its ``flow.source``), :attr:`factory` (the
    ``cv2.optflow`` function that creates it) and :attr:`channels` (1: grey input, 3: BGR).
    The flow follows DIS's convention: ``image0(x) ≈ image1(x + flow(x))``.
    """

    name = ""
    factory = ""
    channels = 1

    def __init__(self) -> None:
        optflow = getattr(cv2, "optflow", None)
        if optflow is None or not hasattr(optflow, self.factory):
            raise ImportError(
                f"flow={self.name} needs OpenCV's contrib modules (cv2.optflow.{self.factory}), "
                f"which this cv2 ({cv2.__version__}, {cv2.__file__}) lacks: replace "
                "opencv-python-headless by opencv-contrib-python-headless (`make install` does "
                "it; the two must not be installed together)"
            )
        self._algorithm: Any = None

    def key(self) -> dict[str, Any]:
        """Everything about the estimator that changes its output (for the cache key)."""
        return {"estimator": self.name, "opencv": cv2.__version__}

    def prepare(self, rgb: np.ndarray) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB → the algorithm's input: ``(H, W)`` grey or ``(H, W, 3)``
        BGR uint8."""
        code = cv2.COLOR_RGB2GRAY if self.channels == 1 else cv2.COLOR_RGB2BGR
        return cv2.cvtColor(rgb, code)

    def __call__(self, image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        """Flow from ``image0`` to ``image1``: ``(H, W, 2)`` float32 pixels."""
        if self._algorithm is None:
            self._algorithm = getattr(cv2.optflow, self.factory)()
        return self._algorithm.calc(image0, image1, None)

    def __getstate__(self) -> dict[str, Any]:
        # cv2 objects do not pickle; each DataLoader worker builds its own.
        return {**self.__dict__, "_algorithm": None}


class DeepFlowEstimator(OpenCVFlowEstimator):
    """DeepFlow (Weinzaepfel et al. 2013): variational, with deep matching's constraints."""

    name, factory = "deepflow", "createOptFlow_DeepFlow"


class TVL1Estimator(OpenCVFlowEstimator):
    """Dual TV-L1 (Zach et al. 2007): total-variation regularised, L1 data term."""

    name, factory = "tvl1", "createOptFlow_DualTVL1"


class PCAFlowEstimator(OpenCVFlowEstimator):
    """PCA-Flow (Wulff & Black 2015): sparse matches fit by a learned low-dimensional basis."""

    name, factory = "pcaflow", "createOptFlow_PCAFlow"


class FarnebackEstimator(OpenCVFlowEstimator):
    """Farnebäck (2003): polynomial expansion, coarse to fine."""

    name, factory = "farneback", "createOptFlow_Farneback"


class SparseToDenseEstimator(OpenCVFlowEstimator):
    """Sparse Lucas-Kanade matches interpolated densely (``calcOpticalFlowSparseToDense``)."""

    name, factory = "sparse_to_dense", "createOptFlow_SparseToDense"


class DenseRLOFEstimator(OpenCVFlowEstimator):
    """Dense robust local optical flow (Senst et al.), on colour images."""

    name, factory, channels = "rlof", "createOptFlow_DenseRLOF", 3


#: ``flow.source`` of an estimator → its class; its constructor takes the rest of ``flow.*`` but
#: ``height`` and ``width`` (``learned``: the framework's own network, :mod:`.learned`).
ESTIMATORS: dict[str, type] = {
    "dis": DISFlowEstimator,
    **{
        cls.name: cls
        for cls in (
            DeepFlowEstimator,
            TVL1Estimator,
            PCAFlowEstimator,
            FarnebackEstimator,
            SparseToDenseEstimator,
            DenseRLOFEstimator,
            LearnedFlowEstimator,
        )
    },
}


@dataclass(frozen=True)
class ExactFlow:
    """``flow=exact``: the exact reprojection flow of a synthetic scene, corrupted.

    Attributes:
        noise_std: standard deviation of the Gaussian noise added to every vector, pixels of the
            model input.
        outlier_fraction: fraction of pixels whose vector is replaced by a uniform random one.
    """

    noise_std: float = 0.3
    outlier_fraction: float = 0.01
    source: ClassVar[str] = "exact"

    def __post_init__(self) -> None:
        if not self.noise_std >= 0:
            raise ValueError(f"flow.noise_std must be ≥ 0 pixels, got {self.noise_std}")
        if not 0.0 <= self.outlier_fraction <= 1.0:
            raise ValueError(
                f"flow.outlier_fraction must be in [0, 1], got {self.outlier_fraction}"
            )


@dataclass(frozen=True)
class EstimatedFlow:
    """Flow estimated from images (``flow=dis``): the estimator and the image size it runs at.

    Attributes:
        estimator: a :class:`FlowEstimator`.
        height, width: the size of the images the estimator sees, pixels (synthetic: the render
            size; KITTI: the size the real images are resized to). None: the dataset's own
            (synthetic :data:`~mfg_lightning.data.rendered.RENDER_SIZE`, KITTI native).
    """

    estimator: FlowEstimator
    height: int | None = None
    width: int | None = None

    def __post_init__(self) -> None:
        if (self.height is None) != (self.width is None):
            raise ValueError("set both flow.height and flow.width, or neither")
        for key in ("height", "width"):
            value = getattr(self, key)
            if value is not None and (isinstance(value, bool) or int(value) != value or value <= 0):
                raise ValueError(f"flow.{key} must be a positive number of pixels, got {value!r}")

    @property
    def source(self) -> str:
        return self.estimator.name

    def image_hw(self, native: tuple[int, int]) -> tuple[int, int]:
        """The estimation size: ``(flow.height, flow.width)``, or ``native`` where unset."""
        if self.height is None or self.width is None:
            return native
        return int(self.height), int(self.width)

    def key(self) -> dict[str, Any]:
        return {**self.estimator.key(), "source": self.source}


@dataclass(frozen=True)
class FlowFiles:
    """``flow=files``: the user's own flow, ``<dir>/<seq>/<src:06d>_<tgt:06d>.<ext>``."""

    dir: str
    source: ClassVar[str] = "files"

    def __post_init__(self) -> None:
        if self.dir is None or str(self.dir).strip() in ("", "???", "None", "null"):
            raise ValueError(
                "flow=files needs flow.dir: the directory holding "
                "<flow.dir>/<seq>/<src:06d>_<tgt:06d>.<flo|png|npy|npz>"
            )


@dataclass(frozen=True)
class GroundTruthFlow:
    """``flow=ground_truth``: the flow files the dataset ships (Virtual KITTI's rendered flow),
    read as they are: no noise, no estimation."""

    source: ClassVar[str] = "ground_truth"


FlowSource = ExactFlow | EstimatedFlow | FlowFiles | GroundTruthFlow
_PLAIN_SOURCES = {cls.source: cls for cls in (ExactFlow, FlowFiles, GroundTruthFlow)}


def flow_sources() -> list[str]:
    """Every valid ``flow.source``: ``exact``, ``files``, ``ground_truth`` and the estimators."""
    return sorted({*_PLAIN_SOURCES, *ESTIMATORS})


def parse_flow(cfg: Mapping[str, Any] | FlowSource | None, default: str) -> FlowSource:
    """The flow source a ``flow`` config (a ``conf/flow/*.yaml``) describes.

    Args:
        cfg: ``{"source": <name>, **settings}``; None: ``{"source": default}`` with the
            settings' defaults. A parsed source is returned as it is.
        default: the dataset's default source.

    Raises:
        ValueError: an unknown source or setting, naming the ``flow.*`` key.
    """
    if isinstance(cfg, (ExactFlow, EstimatedFlow, FlowFiles, GroundTruthFlow)):
        return cfg
    settings = dict(cfg or {})
    source = settings.pop("source", default)
    known = flow_sources()
    if source not in known:
        raise ValueError(
            f"flow.source={source!r} is not a flow source; choose one of {', '.join(known)} "
            "(flow=<name>, the files of conf/flow/)"
        )
    fields: dict[str, Any] = {}
    if source in _PLAIN_SOURCES:
        cls: Any = _PLAIN_SOURCES[source]
    else:
        fields = {k: settings.pop(k) for k in ("height", "width") if k in settings}
        cls = ESTIMATORS[source]
    import inspect

    accepted = set(inspect.signature(cls).parameters)
    unknown = sorted(set(settings) - accepted)
    if unknown:
        extra = {"height", "width"} if source in ESTIMATORS else set()
        known_keys = sorted(accepted | extra)
        raise ValueError(
            f"unknown setting(s) {', '.join(f'flow.{k}' for k in unknown)} for "
            f"flow.source={source}; known: {', '.join(known_keys)}"
        )
    made = cls(**settings)
    if source in ESTIMATORS:
        return EstimatedFlow(made, **fields)
    return made


@dataclass(frozen=True)
class FlowCache:
    """On-disk cache of computed flow (and resized RGB) at the model's input size.

    ``<root>/<seq>@<H>x<W>/<src:06d>_<tgt:06d>.npy`` holds ``(h, w, 2)`` float32 flow (pixels of
    the ``h × w`` input size) computed on ``H × W`` images; ``<root>/<seq>_rgb/<frame:06d>.npy``
    the ``(h, w, 3)`` uint8 source image at the input size, so that a cached epoch decodes no
    PNG at all. ``root`` is ``<cache_dir>/<namespace>/<key>`` (``kitti_flow`` for KITTI,
    ``synthetic_flow`` for rendered synthetic worlds) and ``<root>/meta.json`` records what the
    key stands for. Several arrays of one sample go into one ``.npz`` (:meth:`store_arrays`).
    """

    root: Path

    @classmethod
    def create(
        cls, cache_dir: str | os.PathLike, key: dict[str, Any], namespace: str = "kitti_flow"
    ) -> FlowCache:
        text = json.dumps(key, sort_keys=True)
        digest = hashlib.sha256(text.encode()).hexdigest()[:16]
        root = Path(cache_dir).expanduser() / namespace / digest
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

    def load_arrays(self, path: Path, names: tuple[str, ...]) -> dict[str, np.ndarray] | None:
        """The named arrays of an ``.npz`` written by :meth:`store_arrays`, or None if the file
        is absent, unreadable or lacks one of them (then it is recomputed)."""
        try:
            with np.load(path, allow_pickle=False) as archive:
                return {name: archive[name] for name in names}
        except (FileNotFoundError, ValueError, OSError, EOFError, KeyError):
            return None
        except zipfile.BadZipFile:
            return None

    def store_arrays(self, path: Path, arrays: dict[str, np.ndarray]) -> None:
        """Write ``arrays`` as one uncompressed ``.npz`` (atomically)."""
        buf = io.BytesIO()
        # (ascontiguousarray would turn a 0-d array into a 1-d one)
        np.savez(buf, **{k: np.require(v, requirements="C") for k, v in arrays.items()})
        atomic_write_bytes(path, buf.getvalue())
