"""Geometry runs in float32 (or float64) whatever the autocast around it: :func:`full_precision`
widens float16 / bfloat16 arguments and turns autocast off inside."""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import torch
from torch import Tensor

# --------------------------------------------------------------------------------------------
# Precision: geometry runs in float32 (or float64) whatever the autocast around it
# --------------------------------------------------------------------------------------------

#: Device types on which ``torch.autocast`` can be active.
_AUTOCAST_DEVICES = ("cpu", "cuda", "mps", "xpu")
#: The dtypes that :func:`to_float32` widens.
_LOW_PRECISION = (torch.float16, torch.bfloat16)

F = TypeVar("F", bound=Callable[..., Any])


def autocast_devices() -> tuple[str, ...]:
    """The device types on which ``torch.autocast`` is active here (empty outside autocast)."""
    return tuple(d for d in _AUTOCAST_DEVICES if torch.is_autocast_enabled(d))


@contextlib.contextmanager
def float32_math() -> Iterator[None]:
    """Turn autocast off, on every device where it is on, for the body.

    Under ``trainer.precision=bf16-mixed`` (or ``16-mixed``) Lightning runs the whole step under
    autocast, which would run every matrix product of the body (the recovery's pseudo-inverse
    product, ``so3_exp``'s ``W @ W``, ``reprojection_flow``'s einsum) in the low precision. Inside
    this context ops run in their inputs' dtype; outside autocast it does nothing.
    """
    with contextlib.ExitStack() as stack:
        for device in autocast_devices():
            stack.enter_context(torch.autocast(device, enabled=False))
        yield


def to_float32(x: Any) -> Any:
    """``x`` as float32 if it is a float16 / bfloat16 tensor; anything else (float32, float64,
    integer and bool tensors, non-tensors) unchanged."""
    return x.float() if isinstance(x, Tensor) and x.dtype in _LOW_PRECISION else x


def full_precision(fn: F) -> F:
    """Decorator: run ``fn`` in float32 whatever the caller's precision.

    Inside, autocast is off (:func:`float32_math`) and float16 / bfloat16 tensor arguments are
    widened to float32 (:func:`to_float32`); float32 and float64 arguments are passed as they are,
    so without autocast and without low-precision arguments ``fn`` runs exactly as undecorated (the
    check costs about a microsecond). Used by the geometry, the losses, object motion and the
    metrics, so that any caller under autocast gets float32 answers: with its intrinsics cast to
    bfloat16 (fx 74.145 → 74.0) the recovery of ``(t, ω)`` from exact fields erred by up to
    2.2e-3 m and 8.5e-5 rad; decorated, it gives float32's answer to 1e-5 m and 1e-7 rad
    (``tests/test_precision.py``).
    """

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        devices = autocast_devices()
        low = any(
            isinstance(a, Tensor) and a.dtype in _LOW_PRECISION for a in (*args, *kwargs.values())
        )
        if not devices and not low:
            return fn(*args, **kwargs)
        args = tuple(to_float32(a) for a in args)
        kwargs = {k: to_float32(v) for k, v in kwargs.items()}
        with float32_math():
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
