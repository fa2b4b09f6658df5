"""``flow=learned``: the framework's own optical-flow network (:mod:`.pwc`, PWC-Net's design)
as a flow estimator, and its weight files.

A weight file is what ``python -m mfg_lightning.train_flow`` exports (:func:`save_weights`):
a ``torch.save`` dict with ``format`` (:data:`WEIGHTS_FORMAT`), the network's ``config``
(:class:`~mfg_lightning.flow.pwc.PWCConfig`), its ``state_dict`` and the ``provenance`` of the
training (command, commit, steps, data, wall time, CPU). ``flow.weights`` also takes a training
checkpoint of the same network (``checkpoints/*.ckpt`` of a ``train_flow`` run). Without
``flow.weights`` the estimator loads the weights shipped with the package
(:data:`DEFAULT_WEIGHTS`, trained on the rendered worlds of KITTI's training trajectories:
their provenance is in the file and in ``docs/flow.md``).

The estimator's cache key holds the weights' SHA-256: flow estimated with other weights is
never read back.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from mfg_lightning.flow.pwc import PWCFlowNet, config_from

__all__ = [
    "DEFAULT_WEIGHTS",
    "WEIGHTS_FORMAT",
    "LearnedFlowEstimator",
    "load_weights",
    "model_input_flow",
    "save_weights",
]

#: The ``format`` entry of a weight file.
WEIGHTS_FORMAT = "mfg_lightning.flow_net/1"
#: The weights shipped with the package (``flow=learned`` without ``flow.weights``).
DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "pwc_rendered.pt"


def save_weights(
    path: str | Path, net: PWCFlowNet, provenance: dict[str, Any] | None = None
) -> Path:
    """Write ``net``'s weights with its config and ``provenance`` (atomically); return the
    path."""
    from mfg_lightning.core.atomic import atomic_write_bytes

    buffer = io.BytesIO()
    state = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    torch.save(
        {
            "format": WEIGHTS_FORMAT,
            "config": net.config.to_dict(),
            "state_dict": state,
            # plain data only (json's types), so that weights_only loading reads it
            "provenance": json.loads(json.dumps(provenance or {}, default=str)),
        },
        buffer,
    )
    path = Path(path)
    atomic_write_bytes(path, buffer.getvalue())
    return path


def _refuse(path: Path, why: str) -> ValueError:
    return ValueError(
        f"flow.weights={path}: {why}; give a weight file that python -m "
        "mfg_lightning.train_flow exported (flow_net.pt) or one of its checkpoints (*.ckpt)"
    )


def load_weights(path: str | Path) -> tuple[PWCFlowNet, dict[str, Any]]:
    """The network of a weight file or a ``train_flow`` checkpoint, in eval mode, and the
    file's provenance (a checkpoint's: its global step).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a weight file or checkpoint of this network (naming the file and what
            is wrong: unreadable, another format, missing or unexpected weights, wrong shapes).
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"flow.weights: no such file: {path}")
    if not zipfile.is_zipfile(path):
        raise _refuse(path, "not a torch file (a zip archive), or cut short")
    try:
        # (TorchVersion: a str subclass that a provenance's torch.__version__ may have pickled)
        with torch.serialization.safe_globals([torch.torch_version.TorchVersion]):
            data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # (torch raises several kinds for foreign files)
        raise _refuse(path, f"unreadable ({type(err).__name__}: {err})") from None
    if not isinstance(data, dict):
        raise _refuse(path, f"holds a {type(data).__name__}, not a dict")
    if data.get("format") == WEIGHTS_FORMAT:
        config, state, provenance = (
            data.get("config"),
            data.get("state_dict"),
            data.get("provenance") or {},
        )
    elif "flow_net_config" in data and "state_dict" in data:
        config = data["flow_net_config"]
        # the network's place in the module: "net." (train_flow), "flow_net." (end to end)
        prefix = str(data.get("flow_net_prefix", "net."))
        state = {k[len(prefix) :]: v for k, v in data["state_dict"].items() if k.startswith(prefix)}
        provenance = {"checkpoint": str(path), "global_step": data.get("global_step")}
    else:
        what = data.get("format") or ("an MFG checkpoint" if "state_dict" in data else "no format")
        raise _refuse(path, f"not a flow-network file ({what})")
    try:
        net = PWCFlowNet(config_from(config))
    except (TypeError, ValueError) as err:
        raise _refuse(path, f"its network config is invalid ({err})") from None
    if not isinstance(state, dict):
        raise _refuse(path, "it has no state_dict")
    missing, unexpected = (
        net.state_dict().keys() - state.keys(),
        state.keys() - net.state_dict().keys(),
    )
    if missing or unexpected:
        raise _refuse(
            path,
            f"its weights do not fit the network (missing {sorted(missing)[:4]}, unexpected "
            f"{sorted(unexpected)[:4]})",
        )
    try:
        net.load_state_dict(state)
    except RuntimeError as err:
        raise _refuse(path, f"its weights do not fit the network ({err})") from None
    return net.eval(), dict(provenance)


def model_input_flow(full: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """The flow MFG reads under ``flow=learned``, from the estimate at the image size, with
    gradients (end-to-end training, :mod:`mfg_lightning.models.end_to_end`).

    The dataset's path in torch: :class:`~mfg_lightning.data.rendered.RenderedDrivingDataset`
    resizes the estimate (:meth:`LearnedFlowEstimator.estimate_batch`: the network's quarter-size
    output upsampled bilinearly) to the model input with
    :func:`~mfg_lightning.data.transforms.resize_flow`, an area average whose vectors are
    scaled by the size ratios (``u · w / W``, ``v · h / H``). The network's flow is finite
    everywhere, so every pixel counts. Equal to it (to float rounding) where the image size is
    a whole multiple of the model input (192 × 512 → 48 × 128: OpenCV's area average is then
    the block mean that torch's is); tests/test_end_to_end.py compares the two.

    Args:
        full: ``(B, 2, H, W)`` flow, pixels of the image.
        height, width: the model input (at most ``H × W``).

    Returns:
        ``(B, 2, height, width)`` flow, pixels of the model input.
    """
    h, w = full.shape[-2:]
    if (h, w) == (height, width):
        return full
    if height > h or width > w:
        raise ValueError(
            f"the flow is {h} × {w}, smaller than the model input {height} × {width}: render "
            "at least at the input size"
        )
    scale = full.new_tensor([width / w, height / h]).view(1, 2, 1, 1)
    return F.interpolate(full, size=(height, width), mode="area") * scale


def file_digest(path: str | Path) -> str:
    """The SHA-256 of a file, hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


class LearnedFlowEstimator:
    """``flow=learned``: :class:`~mfg_lightning.flow.pwc.PWCFlowNet` on RGB frames.

    Args:
        weights: a weight file or ``train_flow`` checkpoint (None: :data:`DEFAULT_WEIGHTS`).
        device: ``"auto"`` (CUDA when present, else the CPU), ``"cpu"``, ``"cuda"``, ….

    The flow comes at the input size (the network's 1/4-size output upsampled bilinearly;
    any size, padded to a multiple of 32 inside), float32 pixels with
    ``image0(x) ≈ image1(x + flow(x))``. The network is loaded on the first call (a process
    that only reads the cache never loads it).
    """

    name = "learned"

    def __init__(self, weights: str | None = None, device: str = "auto") -> None:
        path = Path(weights).expanduser() if weights else DEFAULT_WEIGHTS
        if not path.is_file():
            hint = "" if weights else " (the package's weights: reinstall, or pass flow.weights)"
            raise FileNotFoundError(f"flow.weights: no such file: {path}{hint}")
        self.weights = path
        self.device = str(device)
        if self.device != "auto":
            torch.device(self.device)  # a malformed device string fails here
        self.digest = file_digest(path)
        self._net: PWCFlowNet | None = None

    def net(self) -> PWCFlowNet:
        """The network, loaded on first use."""
        if self._net is None:
            net, self.provenance = load_weights(self.weights)
            device = self.device
            if device == "auto":
                device = "cuda" if torch.cuda.is_available() else "cpu"
            self._net = net.to(device)
        return self._net

    def key(self) -> dict[str, Any]:
        """Everything about the estimator that changes its output (for the cache key)."""
        return {"estimator": self.name, "weights_sha256": self.digest, "torch": torch.__version__}

    def prepare(self, rgb: np.ndarray) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB, as it is."""
        return np.ascontiguousarray(rgb)

    def estimate_batch(self, images0: torch.Tensor, images1: torch.Tensor) -> torch.Tensor:
        """``(B, 3, H, W)`` uint8 RGB pairs → ``(B, 2, H, W)`` float32 flow (pixels), on the
        estimator's device."""
        net = self.net()
        device = next(net.parameters()).device
        a = images0.to(device).float() / 255.0
        b = images1.to(device).float() / 255.0
        return net.estimate(a, b)

    def __call__(self, image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        """Flow from ``image0`` to ``image1`` (``(H, W, 3)`` uint8 RGB each): ``(H, W, 2)``
        float32 pixels."""
        a = torch.from_numpy(np.ascontiguousarray(image0)).permute(2, 0, 1)[None]
        b = torch.from_numpy(np.ascontiguousarray(image1)).permute(2, 0, 1)[None]
        flow = self.estimate_batch(a, b)[0]
        return np.ascontiguousarray(flow.permute(1, 2, 0).cpu().numpy(), dtype=np.float32)

    def __getstate__(self) -> dict[str, Any]:
        # each process (DataLoader or preparation worker) loads its own copy
        return {**self.__dict__, "_net": None}
