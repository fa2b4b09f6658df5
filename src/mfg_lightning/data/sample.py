"""The sample every dataset yields, its schema, and its validation.

A sample is a ``dict`` of tensors (plus a few identity fields). Every dataset (synthetic, KITTI,
Virtual KITTI, rendered worlds) yields the same keys so the model, losses, metrics and
object-motion code never care where a sample came from. ``H, W`` is the model's input resolution.
:data:`SCHEMA` is the one statement of the keys (shape, dtype, required); the table below, the
sample and batch checks and :func:`model_inputs` are made from it, and the code names the keys by
their constants (:data:`FLOW`, :data:`POSE`, …).

{table}

``pose`` is optional: a dataset of flow without ground truth (``mfg-predict`` on a directory of
flow files) has none; training and evaluation need it (``check_batch_layout(..., needs=(POSE,))``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch

FLOW = "flow"
FLOW_VALID = "flow_valid"
POSE = "pose"
INTRINSICS = "intrinsics"
DEPTH = "depth"
OBJECT_MASK = "object_mask"
OBJECT_FLOW = "object_flow"
RGB = "rgb"
EXACT_FLOW = "exact_flow"
SEQUENCE = "sequence"
FRAME = "frame"
TARGET = "target"
SAMPLE_ID = "sample_id"
#: Batch only, never in a sample: the batch's intrinsics kept on the host when the batch moves to
#: another device (:meth:`mfg_lightning.models.mfg_module.MFGLitModule.transfer_batch_to_device`),
#: so that the closed-form recovery groups samples by intrinsics without reading them back.
INTRINSICS_HOST = "intrinsics_host"


class Field(NamedTuple):
    """One key of :data:`SCHEMA`.

    Attributes:
        shape: of one sample; ``"H"``, ``"W"`` stand for the input resolution; ``None``: not a
            tensor (an identity field).
        dtype: ``"float"`` (any floating point), a torch dtype, or a Python type for identity
            fields.
        required: every sample has it.
        meaning: the documentation.
    """

    shape: tuple[int | str, ...] | None
    dtype: Any
    required: bool
    meaning: str


#: Every key of a sample (in this order in the documentation).
SCHEMA: dict[str, Field] = {
    FLOW: Field((2, "H", "W"), "float", True,
                "optical flow from the source frame to the target frame, pixels at the input "
                "resolution, (u, v)"),
    FLOW_VALID: Field(("H", "W"), torch.bool, True,
                      "pixels whose flow is known (False: invalid / sky / non-finite in the file)"),
    POSE: Field((4, 4), "float", False,
                "relative pose T_src,tgt = camera at the target frame expressed in the camera at "
                "the source frame (metres); see mfg_lightning.core.geometry. Needed for training "
                "and evaluation"),
    INTRINSICS: Field((4,), "float", True, "(fx, fy, cx, cy) in pixels at the input resolution"),
    DEPTH: Field(("H", "W"), "float", False, "depth of the source frame along z, metres; 0 where "
                 "unknown"),
    OBJECT_MASK: Field(("H", "W"), torch.bool, False, "ground-truth independently moving pixels"),
    OBJECT_FLOW: Field((2, "H", "W"), "float", False,
                       "flow due to object motion alone (flow minus the rigid flow), pixels; 0 "
                       "off objects"),
    RGB: Field((3, "H", "W"), torch.uint8, False, "the source frame, for pictures"),
    EXACT_FLOW: Field((2, "H", "W"), "float", False,
                      "the exact flow when flow was estimated (flow=dis on rendered worlds), 0 "
                      "where unknown"),
    SEQUENCE: Field(None, str, True, 'sequence / world name (e.g. "09", "0001")'),
    FRAME: Field(None, int, True, "index of the source frame in its sequence"),
    TARGET: Field(None, int, True, "index of the target frame (frame + 1 usually)"),
    SAMPLE_ID: Field(None, str, True,
                     '"<dataset>/<split>/<sequence>/<frame>-><target>", used in every error '
                     "message about this sample"),
}  # fmt: skip

REQUIRED_KEYS = tuple(k for k, f in SCHEMA.items() if f.required)
OPTIONAL_KEYS = tuple(k for k, f in SCHEMA.items() if not f.required)


def _dtype_name(dtype: Any) -> str:
    if isinstance(dtype, torch.dtype):
        return {torch.bool: "bool", torch.uint8: "uint8"}.get(dtype, str(dtype))
    return dtype if isinstance(dtype, str) else dtype.__name__


def schema_table() -> str:
    """:data:`SCHEMA` as the reStructuredText table of this module's docstring."""
    rows = [("key", "shape / type", "meaning")]
    for key, f in SCHEMA.items():
        shape = (
            ""
            if f.shape is None
            else "(" + ", ".join(map(str, f.shape)) + ("," if len(f.shape) == 1 else "") + ") "
        )
        optional = "" if f.required else "(optional) "
        rows.append((f"``{key}``", f"{shape}{_dtype_name(f.dtype)}", optional + f.meaning))
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    rule = "  ".join("=" * w for w in widths)
    lines = [
        rule,
        "  ".join(c.ljust(w) for c, w in zip(rows[0], widths, strict=True)).rstrip(),
        rule,
    ]
    lines += [
        "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows[1:]
    ]
    return "\n".join([*lines, rule])


__doc__ = __doc__.format(table=schema_table())


def _shape(field: Field, height: int, width: int) -> tuple[int, ...]:
    """A field's sample shape at the input resolution ``height × width``."""
    size = {"H": height, "W": width}
    return tuple(size.get(d, d) for d in field.shape)  # type: ignore[misc, union-attr]


#: The tensor keys of :data:`SCHEMA`.
TENSOR_KEYS = tuple(k for k, f in SCHEMA.items() if f.shape is not None)


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
    flow = torch.where(finite.unsqueeze(-3), flow, 0.0)
    valid = valid & finite
    return flow, valid, n_bad


class ModelInputs(NamedTuple):
    """What the model reads of a batch (:func:`model_inputs`).

    Attributes:
        flow: ``(..., 2, H, W)`` the flow in pixels with its non-finite pixels set to 0.
        valid: ``(..., H, W)`` bool, the flow's validity with those pixels cleared.
        n_bad: how many pixels were non-finite (a 0-dim int64 tensor on the flow's device).
    """

    flow: torch.Tensor
    valid: torch.Tensor
    n_bad: torch.Tensor


def model_inputs(batch: dict[str, Any], flow_key: str = FLOW) -> ModelInputs:
    """The masked flow, the cleaned validity and the bad-pixel count of a sample or batch: what
    every caller that feeds the model (training, evaluation, prediction, scoring, basis analysis)
    reads. :func:`sanitize_flow` of ``batch[flow_key]`` and ``batch[FLOW_VALID]``; no host read.

    Args:
        batch: a sample or a collated batch.
        flow_key: the flow to read (:data:`EXACT_FLOW` for the exact flow of an estimated one).
    """
    return ModelInputs(*sanitize_flow(batch[flow_key], batch[FLOW_VALID]))


def _expected_shapes(height: int, width: int, batch: int | None = None) -> dict[str, tuple]:
    """``{key: shape}`` of every tensor key of :data:`SCHEMA`; with ``batch``, batched."""
    lead = () if batch is None else (batch,)
    return {k: lead + _shape(SCHEMA[k], height, width) for k in TENSOR_KEYS}


def check_sample(sample: dict[str, Any], height: int, width: int) -> None:
    """Raise :class:`SampleError` naming the sample and key if a sample breaks :data:`SCHEMA`.

    Non-finite flow is *not* an error (it is masked by :func:`sanitize_flow`); non-finite poses or
    intrinsics are, since no pixel mask can repair them.

    Args:
        sample: one sample.
        height, width: the model's input resolution in pixels.
    """
    sid = sample.get(SAMPLE_ID, "<unknown sample>")
    for key in REQUIRED_KEYS:
        if key not in sample:
            raise SampleError(f"{sid}: missing key '{key}'")
    for key, shape in _expected_shapes(height, width).items():
        if key in sample and tuple(sample[key].shape) != shape:
            raise SampleError(
                f"{sid}: '{key}' has shape {tuple(sample[key].shape)}, expected {shape}"
            )
    for key, field in SCHEMA.items():
        if key in sample and not _has_dtype(sample[key], field.dtype):
            raise SampleError(f"{sid}: '{key}' is {_type_of(sample[key])}, expected "
                              f"{_dtype_name(field.dtype)}")  # fmt: skip
    for key in (POSE, INTRINSICS):
        if key in sample and not torch.isfinite(sample[key]).all():
            raise SampleError(f"{sid}: '{key}' has non-finite values")
    if (sample[INTRINSICS][:2] <= 0).any():
        raise SampleError(f"{sid}: focal lengths must be positive, got {sample[INTRINSICS][:2]}")


def _has_dtype(value: Any, dtype: Any) -> bool:
    """Whether ``value`` has :class:`Field`'s ``dtype`` (an identity field of type ``int`` may
    also be a 0-dim integer tensor or a numpy integer)."""
    if isinstance(value, torch.Tensor):
        if dtype == "float":
            return value.dtype.is_floating_point
        if dtype is int:
            return not value.dtype.is_floating_point and value.dtype != torch.bool
        return value.dtype == dtype
    if dtype is int:
        return isinstance(value, int) or type(value).__module__ == "numpy"
    return isinstance(value, dtype) if isinstance(dtype, type) else False


def _type_of(value: Any) -> str:
    return str(value.dtype) if isinstance(value, torch.Tensor) else type(value).__name__


def _batch_ids(
    batch: dict[str, Any], rows: torch.Tensor | np.ndarray | None = None, limit: int = 4
) -> str:
    """The ``sample_id`` of the given batch rows (all when None), for error messages."""
    ids = batch.get(SAMPLE_ID)
    if not isinstance(ids, (list, tuple)):
        return "<batch without sample_id>"
    picked = list(ids) if rows is None else [ids[i] for i in rows.tolist() if i < len(ids)]
    more = f" (+{len(picked) - limit} more)" if len(picked) > limit else ""
    return ", ".join(map(str, picked[:limit])) + more


def check_batch(
    batch: dict[str, Any],
    height: int,
    width: int,
    dtype: torch.dtype | None = None,
    needs: tuple[str, ...] = (),
) -> None:
    """Refuse a collated batch that does not fit a model of input size ``height × width``.

    The batch form of :func:`check_sample`, cheap enough for every step (shape comparisons and a
    finiteness test of the ``B × 16`` pose and ``B × 4`` intrinsics numbers, and of depth and
    object flow when present). Non-finite *flow* is not an error: :func:`sanitize_flow` masks it.
    It is :func:`check_batch_layout` (no tensor value is read) followed by
    :func:`raise_on_bad_values` of :func:`batch_value_flags` (one read of ``5 × B`` flags); a
    run checks every batch so (:class:`mfg_lightning.run.agreed_steps.AgreedSteps`).

    Args:
        batch: ``default_collate`` of samples (``flow`` ``(B, 2, H, W)``, ``flow_valid``
            ``(B, H, W)``, ``pose`` ``(B, 4, 4)``, ``intrinsics`` ``(B, 4)``, optional ``depth``
            ``(B, H, W)``, ``object_mask`` ``(B, H, W)``, ``object_flow`` ``(B, 2, H, W)``,
            ``rgb`` ``(B, 3, H, W)``, and ``sample_id`` a list of B strings).
        height, width: the model's input resolution in pixels.
        dtype: the floating-point type the model computes in (its parameters'); None accepts any
            floating-point flow.
        needs: keys :data:`SCHEMA` calls optional that the caller needs (:data:`POSE`).

    Raises:
        SampleError: naming the samples (all of the batch for a shape error, the offending ones
            for non-finite values) and the key.
    """
    check_batch_layout(batch, height, width, dtype, needs)
    raise_on_bad_values(batch, batch_value_flags(batch))


def check_batch_layout(
    batch: dict[str, Any],
    height: int,
    width: int,
    dtype: torch.dtype | None = None,
    needs: tuple[str, ...] = (),
) -> None:
    """The shape and dtype half of :func:`check_batch`: reads no tensor's values, so it never
    waits for a device. Arguments and errors as there; ``needs``: keys that :data:`SCHEMA` calls
    optional but the caller needs (:data:`POSE` for training and evaluation)."""
    if not isinstance(batch, dict):
        raise SampleError(f"a batch must be a dict of tensors, got {type(batch).__name__}")
    for key in (*REQUIRED_KEYS, *needs):
        if key not in batch or (SCHEMA[key].shape is not None and
                                not isinstance(batch[key], torch.Tensor)):  # fmt: skip
            raise SampleError(f"{_batch_ids(batch)}: missing {_kind(key)} '{key}'")
    b = batch[FLOW].shape[0] if batch[FLOW].ndim else 0
    for key, shape in _expected_shapes(height, width, b).items():
        value = batch.get(key)
        if value is not None and tuple(value.shape) != shape:
            raise SampleError(
                f"{_batch_ids(batch)}: '{key}' has shape {tuple(value.shape)}, expected {shape} "
                f"(batch, then the model's {height}×{width} input)"
            )
    flow_dtype = batch[FLOW].dtype
    if not flow_dtype.is_floating_point or (dtype is not None and flow_dtype != dtype):
        wanted = dtype or "floating point"
        raise SampleError(f"{_batch_ids(batch)}: 'flow' is {flow_dtype}, the model needs {wanted}")
    for key in TENSOR_KEYS:
        value = batch.get(key)
        if key != FLOW and value is not None and not _has_dtype(value, SCHEMA[key].dtype):
            wanted = "float" if SCHEMA[key].dtype == "float" else _dtype_name(SCHEMA[key].dtype)
            raise SampleError(f"{_batch_ids(batch)}: '{key}' is {value.dtype}, expected {wanted}")


def _kind(key: str) -> str:
    return "tensor" if SCHEMA[key].shape is not None else "key"


#: The value checks of :func:`batch_value_flags`, one row each: non-finite values of the first
#: four keys, and a focal length that is not positive.
VALUE_CHECKS = (POSE, INTRINSICS, DEPTH, OBJECT_FLOW, "focal")


def batch_value_flags(batch: dict[str, Any]) -> torch.Tensor:
    """The value half of :func:`check_batch`, as tensor operations only (no synchronisation).

    Args:
        batch: a batch that passed :func:`check_batch_layout`.

    Returns:
        ``(len(VALUE_CHECKS), B)`` bool on the batch's device: row ``k`` marks the samples that
        fail check ``VALUE_CHECKS[k]`` (rows of absent keys are all False).
    """
    b = batch[FLOW].shape[0]
    rows = []
    for key in VALUE_CHECKS[:-1]:
        value = batch.get(key)
        if value is None:
            rows.append(torch.zeros(b, dtype=torch.bool, device=batch[FLOW].device))
        else:
            rows.append(~torch.isfinite(value.reshape(b, -1)).all(dim=1))
    rows.append((batch[INTRINSICS][:, :2] <= 0).any(dim=1))
    return torch.stack([r.to(batch[FLOW].device) for r in rows])


def raise_on_bad_values(batch: dict[str, Any], flags: torch.Tensor | np.ndarray) -> None:
    """Raise :class:`SampleError` for the first failed check of :func:`batch_value_flags`'
    ``flags``, naming the failing samples (read from ``batch["sample_id"]``) and the key.

    A tensor is read (on a device, a wait for it); an array is what a caller already copied to
    the host (``Tensor.numpy()``, which refuses device tensors: never a wait)."""
    if isinstance(flags, torch.Tensor):
        flags = flags.cpu().numpy()
    if not flags.any():
        return
    for check, bad in zip(VALUE_CHECKS, flags, strict=True):
        if not bad.any():
            continue
        ids = _batch_ids(batch, bad.nonzero()[0])
        if check == "focal":
            raise SampleError(f"{ids}: focal lengths must be positive")
        raise SampleError(f"{ids}: '{check}' has non-finite values")
