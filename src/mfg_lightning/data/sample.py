"""The sample every dataset yields, and its validation.

A sample is a ``dict`` of tensors (plus a few identity fields). Every dataset (synthetic, KITTI,
Virtual KITTI) yields the same keys so the model, losses, metrics and object-motion code never
care where a sample came from. ``H, W`` is the model's input resolution.

==================  ===================  ==================================================
key                 shape / type         meaning
==================  ===================  ==================================================
``flow``            ``(2, H, W)`` f32    optical flow from the source frame to the target
                                         frame, pixels at the input resolution, (u, v)
``flow_valid``      ``(H, W)`` bool      pixels whose flow is known (False: invalid / sky /
                                         non-finite in the file)
``pose``            ``(4, 4)`` f32       relative pose ``T_src,tgt`` = camera at the target
                                         frame expressed in the camera at the source frame
                                         (metres); see :mod:`mfg_lightning.core.geometry`
``intrinsics``      ``(4,)`` f32         ``(fx, fy, cx, cy)`` in pixels at the input resolution
``depth``           ``(H, W)`` f32       (optional) depth of the source frame along z, metres;
                                         0 where unknown
``object_mask``     ``(H, W)`` bool      (optional) ground-truth independently moving pixels
``object_flow``     ``(2, H, W)`` f32    (optional) flow due to object motion alone (flow minus
                                         the rigid flow), pixels; 0 off objects
``rgb``             ``(3, H, W)`` uint8  (optional) the source frame, for pictures
``exact_flow``      ``(2, H, W)`` f32    (optional) the exact flow when ``flow`` was estimated
                                         (``flow=dis`` on rendered worlds), 0 where unknown
``sequence``        ``str``              sequence / world name (e.g. ``"09"``, ``"0001"``)
``frame``           ``int``              index of the source frame in its sequence
``target``          ``int``              index of the target frame (``frame + 1`` usually)
``sample_id``       ``str``              ``"<dataset>/<split>/<sequence>/<frame>-><target>"``,
                                         used in every error message about this sample
==================  ===================  ==================================================
"""

from __future__ import annotations

from typing import Any

import torch

REQUIRED_KEYS = (
    "flow",
    "flow_valid",
    "pose",
    "intrinsics",
    "sequence",
    "frame",
    "target",
    "sample_id",
)
OPTIONAL_KEYS = ("depth", "object_mask", "object_flow", "rgb", "exact_flow")


class SampleError(ValueError):
    """A sample is malformed; the message names the sample and the offending key."""


def sanitize_flow(
    flow: torch.Tensor, valid: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mask non-finite flow pixels.

    Tensor operations only: nothing is read back from the device, so the training step that
    calls this on every batch never waits for it (the count is read when it is logged).

    Args:
        flow: ``(..., 2, H, W)`` flow in pixels.
        valid: ``(..., H, W)`` validity mask.

    Returns:
        ``(flow, valid, n_bad)``: flow with non-finite pixels set to 0, the mask with them
        cleared, and how many pixels were non-finite (a 0-dim int64 tensor on the flow's
        device; ``int(n_bad)`` reads it).
    """
    finite = torch.isfinite(flow).all(dim=-3)
    n_bad = (~finite).sum()
    # Always masked: the same values where every pixel is finite, and no test of n_bad.
    flow = torch.where(finite.unsqueeze(-3), flow, torch.zeros_like(flow))
    valid = valid & finite
    return flow, valid, n_bad


def check_sample(sample: dict[str, Any], height: int, width: int) -> None:
    """Raise :class:`SampleError` naming the sample and key if a sample breaks the schema.

    Non-finite flow is *not* an error (it is masked by :func:`sanitize_flow`); non-finite poses or
    intrinsics are, since no pixel mask can repair them.
    """
    sid = sample.get("sample_id", "<unknown sample>")
    for key in REQUIRED_KEYS:
        if key not in sample:
            raise SampleError(f"{sid}: missing key '{key}'")
    expected = {
        "flow": (2, height, width),
        "flow_valid": (height, width),
        "pose": (4, 4),
        "intrinsics": (4,),
        "depth": (height, width),
        "object_mask": (height, width),
        "object_flow": (2, height, width),
        "rgb": (3, height, width),
        "exact_flow": (2, height, width),
    }
    for key, shape in expected.items():
        if key in sample and tuple(sample[key].shape) != shape:
            raise SampleError(
                f"{sid}: '{key}' has shape {tuple(sample[key].shape)}, expected {shape}"
            )
    for key in ("pose", "intrinsics"):
        if not torch.isfinite(sample[key]).all():
            raise SampleError(f"{sid}: '{key}' has non-finite values")
    if (sample["intrinsics"][:2] <= 0).any():
        raise SampleError(f"{sid}: focal lengths must be positive, got {sample['intrinsics'][:2]}")


def _batch_ids(batch: dict[str, Any], rows: torch.Tensor | None = None, limit: int = 4) -> str:
    """The ``sample_id`` of the given batch rows (all when None), for error messages."""
    ids = batch.get("sample_id")
    if not isinstance(ids, (list, tuple)):
        return "<batch without sample_id>"
    picked = list(ids) if rows is None else [ids[i] for i in rows.tolist() if i < len(ids)]
    more = f" (+{len(picked) - limit} more)" if len(picked) > limit else ""
    return ", ".join(map(str, picked[:limit])) + more


def check_batch(
    batch: dict[str, Any], height: int, width: int, dtype: torch.dtype | None = None
) -> None:
    """Refuse a collated batch that does not fit a model of input size ``height × width``.

    The batch form of :func:`check_sample`, cheap enough for every step (shape comparisons and a
    finiteness test of the ``B × 16`` pose and ``B × 4`` intrinsics numbers, and of depth and
    object flow when present). Non-finite *flow* is not an error: :func:`sanitize_flow` masks it.
    It is :func:`check_batch_layout` (no tensor value is read) followed by
    :func:`raise_on_bad_values` of :func:`batch_value_flags` (one read of ``5 × B`` flags), the
    two halves a caller on an accelerator runs apart (:class:`mfg_lightning.run.callbacks.
    BatchChecks`).

    Args:
        batch: ``default_collate`` of samples (``flow`` ``(B, 2, H, W)``, ``flow_valid``
            ``(B, H, W)``, ``pose`` ``(B, 4, 4)``, ``intrinsics`` ``(B, 4)``, optional ``depth``
            ``(B, H, W)``, ``object_mask`` ``(B, H, W)``, ``object_flow`` ``(B, 2, H, W)``,
            ``rgb`` ``(B, 3, H, W)``, and ``sample_id`` a list of B strings).
        height, width: the model's input resolution in pixels.
        dtype: the floating-point type the model computes in (its parameters'); None accepts any
            floating-point flow.

    Raises:
        SampleError: naming the samples (all of the batch for a shape error, the offending ones
            for non-finite values) and the key.
    """
    check_batch_layout(batch, height, width, dtype)
    raise_on_bad_values(batch, batch_value_flags(batch))


def check_batch_layout(
    batch: dict[str, Any], height: int, width: int, dtype: torch.dtype | None = None
) -> None:
    """The shape and dtype half of :func:`check_batch`: reads no tensor's values, so it never
    waits for a device. Arguments and errors as there."""
    if not isinstance(batch, dict):
        raise SampleError(f"a batch must be a dict of tensors, got {type(batch).__name__}")
    for key in ("flow", "flow_valid", "pose", "intrinsics"):
        if not isinstance(batch.get(key), torch.Tensor):
            raise SampleError(f"{_batch_ids(batch)}: missing tensor '{key}'")
    b = batch["flow"].shape[0] if batch["flow"].ndim else 0
    expected = {
        "flow": (b, 2, height, width),
        "flow_valid": (b, height, width),
        "pose": (b, 4, 4),
        "intrinsics": (b, 4),
        "depth": (b, height, width),
        "object_mask": (b, height, width),
        "object_flow": (b, 2, height, width),
        "rgb": (b, 3, height, width),
    }
    for key, shape in expected.items():
        value = batch.get(key)
        if value is not None and tuple(value.shape) != shape:
            raise SampleError(
                f"{_batch_ids(batch)}: '{key}' has shape {tuple(value.shape)}, expected {shape} "
                f"(batch, then the model's {height}×{width} input)"
            )
    flow_dtype = batch["flow"].dtype
    if not flow_dtype.is_floating_point or (dtype is not None and flow_dtype != dtype):
        wanted = dtype or "floating point"
        raise SampleError(f"{_batch_ids(batch)}: 'flow' is {flow_dtype}, the model needs {wanted}")
    if batch["flow_valid"].dtype != torch.bool:
        raise SampleError(
            f"{_batch_ids(batch)}: 'flow_valid' is {batch['flow_valid'].dtype}, expected bool"
        )
    for key in ("pose", "intrinsics", "depth", "object_flow"):
        value = batch.get(key)
        if value is not None and not value.dtype.is_floating_point:
            raise SampleError(f"{_batch_ids(batch)}: '{key}' is {value.dtype}, expected float")


#: The value checks of :func:`batch_value_flags`, one row each: non-finite values of the first
#: four keys, and a focal length that is not positive.
VALUE_CHECKS = ("pose", "intrinsics", "depth", "object_flow", "focal")


def batch_value_flags(batch: dict[str, Any]) -> torch.Tensor:
    """The value half of :func:`check_batch`, as tensor operations only (no synchronisation).

    Args:
        batch: a batch that passed :func:`check_batch_layout`.

    Returns:
        ``(len(VALUE_CHECKS), B)`` bool on the batch's device: row ``k`` marks the samples that
        fail check ``VALUE_CHECKS[k]`` (rows of absent keys are all False).
    """
    b = batch["flow"].shape[0]
    rows = []
    for key in VALUE_CHECKS[:-1]:
        value = batch.get(key)
        if value is None:
            rows.append(torch.zeros(b, dtype=torch.bool, device=batch["flow"].device))
        else:
            rows.append(~torch.isfinite(value.reshape(b, -1)).all(dim=1))
    rows.append((batch["intrinsics"][:, :2] <= 0).any(dim=1))
    return torch.stack([r.to(batch["flow"].device) for r in rows])


def raise_on_bad_values(batch: dict[str, Any], flags: torch.Tensor) -> None:
    """Raise :class:`SampleError` for the first failed check of :func:`batch_value_flags`'
    ``flags``, naming the failing samples (read from ``batch["sample_id"]``) and the key.
    Reads ``flags``: pass them on the host to avoid waiting for a device."""
    flags = flags.cpu()
    if not flags.any():
        return
    for check, bad in zip(VALUE_CHECKS, flags, strict=True):
        if not bad.any():
            continue
        ids = _batch_ids(batch, bad.nonzero().flatten())
        if check == "focal":
            raise SampleError(f"{ids}: focal lengths must be positive")
        raise SampleError(f"{ids}: '{check}' has non-finite values")
