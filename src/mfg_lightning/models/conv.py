"""The encoder's convolutions in three interchangeable implementations
(``model.net.conv_impl``).

On small feature maps oneDNN's convolution kernels run far below the machine's GEMM peak (the
per-layer tables of ``bench/results/throughput.md``: the 1000 × 512 3 × 3 hidden convolution on
its 2 × 4 map, forward and backward, at under a tenth of the bfloat16 GEMM peak on AVX-512),
and which lowering is fastest depends on the layer, the CPU, the dtype and the batch. So every
convolution of the encoder is a :class:`SwitchableConv2d`, an ``nn.Conv2d`` with the same
parameters (checkpoints are the same whatever runs) whose forward is one of:

* ``native``: PyTorch's own ``nn.Conv2d`` on a contiguous (NCHW) input: oneDNN on a CPU;
* ``im2col``: :func:`im2col_conv2d`, every output pixel's receptive field gathered into one row
  of a matrix and one matrix product with the flattened weights (the GEMM kernels run near the
  peak where a convolution kernel does not);
* ``channels_last``: PyTorch's convolution on a channels-last (NHWC) input, oneDNN's other
  layout.

``model.net.conv_impl`` is one of them for every layer, a list with one per layer (in module
order), or ``auto``: a training run resolves ``auto`` from its CPU kind's row of
``conf/cpu_defaults.yaml`` (:mod:`mfg_lightning.run.run_choices`) before it builds the network,
and records the value in its ``config.yaml``. A network built with ``auto`` outside a training
run computes ``native``.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

#: The implementations a :class:`SwitchableConv2d` runs.
CONV_IMPLS = ("native", "im2col", "channels_last")
#: ``model.net.conv_impl`` values: one implementation for every layer, or ``auto``.
CONV_IMPL_SETTINGS = ("auto", *CONV_IMPLS)
AUTO = "auto"


def check_conv_impl(value: str) -> str:
    """``value`` if it is a ``model.net.conv_impl`` setting (:data:`CONV_IMPL_SETTINGS`).

    Raises:
        ValueError: naming the key and the accepted values.
    """
    if value not in CONV_IMPL_SETTINGS:
        raise ValueError(
            f"model.net.conv_impl must be one of {', '.join(CONV_IMPL_SETTINGS)}, got {value!r}"
        )
    return value


def per_layer_impls(value: str | Sequence[str], layers: int) -> list[str]:
    """``model.net.conv_impl`` as one implementation per convolution: a setting
    (:data:`CONV_IMPL_SETTINGS`) repeated, or a list of ``layers`` of them (a run's recorded
    choice, in module order).

    Raises:
        ValueError: naming the key, for an unknown value or a list of another length.
    """
    if isinstance(value, str):
        return [check_conv_impl(value)] * layers
    impls = [str(v) for v in value]
    if len(impls) != layers:
        raise ValueError(
            f"model.net.conv_impl lists {len(impls)} implementations, but the network has "
            f"{layers} convolutions (one per convolution, in module order, or one setting)"
        )
    for impl in impls:
        check_conv_impl(impl)
    return impls


def im2col_conv2d(
    x: Tensor,
    weight: Tensor,
    bias: Tensor | None,
    stride: Sequence[int],
    padding: Sequence[int],
    dilation: Sequence[int] = (1, 1),
) -> Tensor:
    """A 2-D convolution (``groups=1``, zero padding) as one gather and one matrix product.

    Every output pixel's receptive field (``C · kh · kw`` values, in the weight's own order)
    becomes one row of an ``(N · Ho · Wo, C · kh · kw)`` matrix, which one GEMM multiplies with
    the weights viewed as ``(C_out, C · kh · kw)`` (no copy of the weights). The gather is
    ``F.unfold`` (im2col), whose backward is one ``col2im`` that sums the overlapping windows'
    gradients back into the input: about half the time of the same gather built from
    ``Tensor.unfold`` views, whose generic backward dominated the deepest layer's step
    (bench/results/throughput.md, "Per-layer kernels"). The weight gradient is one GEMM of the
    output gradient with the gathered rows. Under autocast the input is cast before the gather
    (the rows are ``kh · kw / (sh · sw)`` times the input), as autocast casts the GEMM's operands.

    Args:
        x: ``(N, C, H, W)`` input, any memory format.
        weight: ``(C_out, C, kh, kw)``.
        bias: ``(C_out,)`` or None.
        stride, padding, dilation: ``(rows, columns)``, pixels.

    Returns:
        ``(N, C_out, Ho, Wo)`` in channels-last memory (the GEMM's rows are output pixels), the
        values of ``F.conv2d(x, weight, bias, stride, padding, dilation)`` up to rounding.
    """
    if torch.is_autocast_enabled(x.device.type):
        x = x.to(torch.get_autocast_dtype(x.device.type))
    n, c, h, w = x.shape
    c_out, _, kh, kw = weight.shape
    (sh, sw), (ph, pw), (dh, dw) = stride, padding, dilation
    ho = (h + 2 * ph - dh * (kh - 1) - 1) // sh + 1
    wo = (w + 2 * pw - dw * (kw - 1) - 1) // sw + 1
    # (N, C · kh · kw, Ho · Wo), rows in the weight's (C, kh, kw) order; contiguous NCHW first,
    # which F.unfold reads fastest whatever the input's memory format.
    cols = F.unfold(x.contiguous(), (kh, kw), dilation=(dh, dw), padding=(ph, pw), stride=(sh, sw))
    rows = cols.transpose(1, 2).reshape(n * ho * wo, c * kh * kw)
    out = F.linear(rows, weight.flatten(1), bias)  # (N · Ho · Wo, C_out)
    return out.view(n, ho, wo, c_out).permute(0, 3, 1, 2)


class SwitchableConv2d(nn.Conv2d):
    """An ``nn.Conv2d`` whose forward runs one of :data:`CONV_IMPLS` on its own weights.

    Same constructor, parameters and ``state_dict`` as ``nn.Conv2d``; ``impl`` (``native``,
    ``im2col``, ``channels_last``, or ``auto``, which computes ``native``) can change at any
    time, between steps or after loading a checkpoint.
    Input ``(N, C, H, W)``, output ``(N, C_out, Ho, Wo)``; its memory format depends on ``impl``
    (``native`` NCHW, the other two NHWC), and each implementation converts its input itself.
    """

    def __init__(self, *args: object, impl: str = "native", **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.impl = impl

    @property
    def impl(self) -> str:
        """The implementation the forward runs (``auto``: pending a choice, runs ``native``)."""
        return self._impl

    @impl.setter
    def impl(self, value: str) -> None:
        check_conv_impl(value)
        if value == "im2col" and not self.im2col_supported:
            raise ValueError(
                f"model.net.conv_impl=im2col supports groups=1, zero padding and numeric padding "
                f"only, not {self}"
            )
        self._impl = value

    @property
    def im2col_supported(self) -> bool:
        """Whether :func:`im2col_conv2d` computes this layer (groups 1, numeric zero padding)."""
        return (
            self.groups == 1 and self.padding_mode == "zeros" and not isinstance(self.padding, str)
        )

    def candidates(self) -> tuple[str, ...]:
        """The implementations ``auto`` measures for this layer."""
        return tuple(i for i in CONV_IMPLS if i != "im2col" or self.im2col_supported)

    def forward(self, x: Tensor) -> Tensor:
        if self._impl == "im2col":
            padding = self.padding  # numeric: the impl setter refuses a string padding
            assert not isinstance(padding, str)
            return im2col_conv2d(x, self.weight, self.bias, self.stride, padding, self.dilation)
        if self._impl == "channels_last":
            return self._conv_forward(
                x.contiguous(memory_format=torch.channels_last), self.weight, self.bias
            )
        # native (and auto before its choice): NCHW, whatever layout the previous layer produced
        return self._conv_forward(x.contiguous(), self.weight, self.bias)

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, impl={self._impl}"

    def geometry(self) -> str:
        """The layer's shape, e.g. ``"512->1000 k3x3 s1x1 p1x1 d1x1 bias"``: a cache key part."""
        kh, kw = self.kernel_size
        parts = [
            f"{self.in_channels}->{self.out_channels}",
            f"k{kh}x{kw}",
            "s{}x{}".format(*self.stride),
            "p{}x{}".format(*self.padding) if not isinstance(self.padding, str) else self.padding,
            "d{}x{}".format(*self.dilation),
            f"g{self.groups}" if self.groups != 1 else "",
            "bias" if self.bias is not None else "nobias",
        ]
        return " ".join(p for p in parts if p)


def switchable_layers(net: nn.Module) -> Iterator[tuple[str, SwitchableConv2d]]:
    """``(name, layer)`` of every :class:`SwitchableConv2d` of ``net``, in module order."""
    for name, module in net.named_modules():
        if isinstance(module, SwitchableConv2d):
            yield name, module


@dataclass(frozen=True)
class LayerInput:
    """What a layer receives in the step: shape ``(N, C, H, W)``, dtype, needs a gradient."""

    shape: tuple[int, ...]
    dtype: torch.dtype
    requires_grad: bool


def _autocast(dtype: torch.dtype) -> torch.autocast:
    """CPU autocast to ``dtype`` (off for float32): how training runs the encoder."""
    return torch.autocast("cpu", dtype=dtype, enabled=dtype != torch.float32)


def layer_inputs(
    net: nn.Module,
    layers: dict[str, SwitchableConv2d],
    flow_shape: tuple[int, ...],
    dtype: torch.dtype,
) -> dict[str, LayerInput]:
    """One forward of ``net`` on zeros of ``flow_shape`` (the training input), recording what each
    layer receives. With gradients on, so that a layer's input needs one exactly when it does
    in training (the flow does not; everything after the first layer does)."""
    seen: dict[str, LayerInput] = {}

    def record(name: str, module: nn.Module, args: tuple[Tensor, ...]) -> None:
        x = args[0]
        seen.setdefault(name, LayerInput(tuple(x.shape), x.dtype, x.requires_grad))

    hooks = [
        layer.register_forward_pre_hook(lambda m, a, name=name: record(name, m, a))
        for name, layer in layers.items()
    ]
    try:
        with _autocast(dtype), torch.enable_grad():
            net(torch.zeros(flow_shape))
    finally:
        for hook in hooks:
            hook.remove()
    return seen
