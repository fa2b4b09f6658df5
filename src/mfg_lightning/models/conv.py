"""The encoder's convolutions in three interchangeable implementations, and the per-machine
choice among them (``model.net.conv_impl``).

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

``auto`` measures the three on this machine, layer by layer (:func:`choose_conv_impls`: forward
+ backward at the training batch and input size, in the dtype training computes in) and keeps
the fastest; the choice is cached per machine under ``paths.cache_dir`` and logged. Until it is
made (evaluation, prediction, a network built outside a training run), ``auto`` runs ``native``.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mfg_lightning.core.atomic import atomic_write_text
from mfg_lightning.core.machine import cpu_model, cpu_vector_features, describe_cpu, isa_caps

log = logging.getLogger(__name__)

#: The implementations a :class:`SwitchableConv2d` runs.
CONV_IMPLS = ("native", "im2col", "channels_last")
#: ``model.net.conv_impl`` values: one implementation for every layer, or ``auto``.
CONV_IMPL_SETTINGS = ("auto", *CONV_IMPLS)
AUTO = "auto"
#: Bumped when an implementation changes, so that old cached choices are measured again.
CACHE_VERSION = 1
#: A measured implementation replaces ``native`` only when it is this much faster (fraction of
#: native's time): on a busy machine two equal kernels differ by a few per cent from run to run.
NATIVE_MARGIN = 0.05
#: Below this share of the CPU time its threads could use, the process timing the convolutions
#: was starved by other work and its times say little (seen on 2 cores: a nice-19 training run
#: beside a 2-thread job got 4 % of its CPU time, a benchmark on the quiet machine 88 %).
BUSY_CPU_SHARE = 0.3
#: A candidate this many times slower than the best in its first timed round is not timed again.
CLEARLY_SLOWER = 2.0


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
    the weights viewed as ``(C_out, C · kh · kw)`` (no copy of the weights). Autograd derives the
    backward: the input gradient is the GEMM with the weights scattered back over the windows
    (overlapping windows summed), the weight gradient one GEMM of the output gradient with the
    gathered rows. Under autocast the input is cast before the gather (the rows are
    ``kh · kw / (sh · sw)`` times the input), as autocast casts the GEMM's operands.

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
    # One copy into a zero-padded contiguous NCHW tensor, whatever the input's memory format: the
    # gather below then reads each window's kw values from one contiguous run.
    padded = x.new_zeros(n, c, h + 2 * ph, w + 2 * pw)
    padded[:, :, ph : ph + h, pw : pw + w] = x
    span_h, span_w = dh * (kh - 1) + 1, dw * (kw - 1) + 1
    windows = padded.unfold(2, span_h, sh).unfold(3, span_w, sw)  # (N, C, Ho, Wo, span_h, span_w)
    if dh > 1 or dw > 1:
        windows = windows[..., ::dh, ::dw]
    ho, wo = windows.shape[2], windows.shape[3]
    # The gather: (N, Ho, Wo, C, kh, kw) made contiguous, one row per output pixel.
    rows = windows.permute(0, 2, 3, 1, 4, 5).reshape(n * ho * wo, c * kh * kw)
    out = F.linear(rows, weight.flatten(1), bias)  # (N · Ho · Wo, C_out)
    return out.view(n, ho, wo, c_out).permute(0, 3, 1, 2)


class SwitchableConv2d(nn.Conv2d):
    """An ``nn.Conv2d`` whose forward runs one of :data:`CONV_IMPLS` on its own weights.

    Same constructor, parameters and ``state_dict`` as ``nn.Conv2d``; ``impl`` (``native``,
    ``im2col``, ``channels_last``, or ``auto``: ``native`` until :func:`choose_conv_impls` picks
    one) can change at any time, between steps or after loading a checkpoint.
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
class ConvChoice:
    """One layer's choice under ``auto``.

    Attributes:
        name: the layer's module name in the network, e.g. ``encoder.14``.
        key: its cache key (:func:`layer_key`): geometry, input, dtype.
        shape: the input it was timed on, ``(N, C, H, W)``.
        ms: forward + backward time of each candidate, milliseconds (the best of the repeats).
        choice: the implementation it runs.
        cached: read from the cache rather than measured now.
    """

    name: str
    key: str
    shape: tuple[int, ...]
    ms: dict[str, float]
    choice: str
    cached: bool

    def describe(self) -> str:
        """One log line: the layer, each candidate's time, the choice."""
        times = ", ".join(f"{impl} {ms:.2f} ms" for impl, ms in self.ms.items())
        return f"{self.name} ({self.key}): {times} -> {self.choice}"


def machine_key(threads: int | None = None) -> dict[str, object]:
    """What a measured time depends on besides the layer: the CPU model and vector features,
    the CPU kernels torch dispatches to and the instruction-set caps set in the environment
    (:func:`~mfg_lightning.core.machine.isa_caps`: a machine imitating a smaller CPU times
    other kernels), torch's version, the thread count and the version of these
    implementations."""
    capability = getattr(torch.backends.cpu, "get_cpu_capability", lambda: "unknown")()
    return {
        "cpu": cpu_model(),
        "features": dict(cpu_vector_features()),
        "torch_cpu_capability": capability,
        "isa_caps": isa_caps(),
        "torch": torch.__version__,
        "threads": threads if threads is not None else torch.get_num_threads(),
        "version": CACHE_VERSION,
    }


def cache_path(cache_dir: str | Path, machine: dict[str, object]) -> Path:
    """``<cache_dir>/conv_impl/<digest of the machine key>.json``: one small file per machine."""
    digest = hashlib.sha256(json.dumps(machine, sort_keys=True).encode()).hexdigest()[:16]
    return Path(cache_dir).expanduser() / "conv_impl" / f"{digest}.json"


def _read_cache(path: Path) -> dict[str, dict]:
    """The cached layers of ``path`` (empty if absent or unreadable: then measured again)."""
    try:
        return dict(json.loads(path.read_text())["layers"])
    except FileNotFoundError:
        return {}
    except (OSError, ValueError, KeyError, TypeError) as err:
        log.warning("conv_impl cache %s is unreadable (%s): measuring again", path, err)
        return {}


@dataclass(frozen=True)
class LayerInput:
    """What a layer receives in the step: shape ``(N, C, H, W)``, dtype, needs a gradient."""

    shape: tuple[int, ...]
    dtype: torch.dtype
    requires_grad: bool


def _autocast(dtype: torch.dtype) -> torch.autocast:
    """CPU autocast to ``dtype`` (off for float32): how training runs the encoder."""
    return torch.autocast("cpu", dtype=dtype, enabled=dtype != torch.float32)


def _layer_inputs(
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


def time_layer(
    layer: SwitchableConv2d,
    given: LayerInput,
    dtype: torch.dtype,
    repeats: int = 3,
    generator: torch.Generator | None = None,
) -> dict[str, float]:
    """Forward + backward milliseconds of each of ``layer``'s candidates on a random input of
    ``given``'s shape: the best of ``repeats`` after one warm-up, the candidates interleaved so
    that a change of the machine's load hits them alike. A candidate more than
    :data:`CLEARLY_SLOWER` times the best after the first timed round is not timed again (im2col
    on a large map, say: it cannot win, and it is the longest to time). On a copy of the layer:
    the network's weights and gradients are untouched. Under ``dtype`` bfloat16/float16 the
    forward runs under CPU autocast and the backward outside it, as in a training step."""
    probe = copy.deepcopy(layer)
    x = torch.randn(given.shape, generator=generator).to(given.dtype)
    x.requires_grad_(given.requires_grad)
    times: dict[str, list[float]] = {impl: [] for impl in layer.candidates()}
    timing = list(times)
    for round_ in range(1 + repeats):
        for impl in timing:
            probe.impl = impl
            start = time.perf_counter()
            with _autocast(dtype):
                y = probe(x)
            forward = time.perf_counter() - start
            grad = torch.ones_like(y)
            start = time.perf_counter()
            y.backward(grad)
            backward = time.perf_counter() - start
            # Set to None as the optimiser's zero_grad does: the next backward writes, not adds.
            for tensor in (x, probe.weight, probe.bias):
                if tensor is not None:
                    tensor.grad = None
            if round_:  # the first round builds oneDNN's primitives and warms the allocator
                times[impl].append(forward + backward)
        if round_ == 1:
            best = min(t[0] for t in times.values())
            timing = [impl for impl in timing if times[impl][0] <= CLEARLY_SLOWER * best]
    return {impl: 1e3 * min(t) for impl, t in times.items()}


def layer_key(layer: SwitchableConv2d, given: LayerInput, dtype: torch.dtype) -> str:
    """A layer's cache key on one machine, e.g. ``"512->1000 k3x3 s1x1 p1x1 d1x1 bias, input
    16x512x2x4 float32 with its gradient, computed in float32"``: the geometry, the input it
    gets (batch included), and the dtype the convolution computes in."""
    shape = "x".join(map(str, given.shape))
    grad = " with its gradient" if given.requires_grad else ""
    return (
        f"{layer.geometry()}, input {shape} {_dtype_name(given.dtype)}{grad}, "
        f"computed in {_dtype_name(dtype)}"
    )


def _dtype_name(dtype: torch.dtype) -> str:
    return str(dtype).removeprefix("torch.")


def pick(ms: dict[str, float], margin: float = NATIVE_MARGIN) -> str:
    """The fastest of the measured implementations; ``native`` unless another is faster by more
    than ``margin`` of native's time."""
    best = min(ms, key=ms.__getitem__)
    if "native" in ms and ms[best] >= (1.0 - margin) * ms["native"]:
        return "native"
    return best


def choose_conv_impls(
    net: nn.Module,
    flow_shape: tuple[int, ...],
    dtype: torch.dtype = torch.float32,
    cache_dir: str | Path | None = None,
    repeats: int = 3,
    min_cpu_share: float = BUSY_CPU_SHARE,
) -> list[ConvChoice]:
    """Give every ``auto`` layer of ``net`` its fastest implementation on this machine.

    Each such layer is timed alone (:func:`time_layer`) on the input it gets in a training step
    on ``flow_shape`` (``(N, 2, H, W)``: the training batch and input size), in ``dtype``
    (float32, or the autocast dtype of a mixed precision), unless ``cache_dir`` holds its time
    for this machine (:func:`machine_key`, :func:`cache_path`); new times are added to that
    file atomically. If this process got less than ``min_cpu_share`` of the CPU time its threads
    could have used while timing, other work had the cores and the times say little: the layers
    timed keep ``native`` and nothing is cached (a warning says so; the next run measures
    again). Layers already set to an implementation are left alone. The global random state is
    not used (measuring leaves a seeded run's random numbers as they were).

    Args:
        net: the network (any module built from :class:`SwitchableConv2d`).
        flow_shape: the training input's shape, ``(N, C, H, W)``.
        dtype: ``torch.float32``, ``torch.bfloat16`` or ``torch.float16``.
        cache_dir: ``paths.cache_dir``; None: measure and keep nothing.
        repeats: timed repeats per candidate (after one warm-up).
        min_cpu_share: the CPU share below which the machine counts as busy (0: never).

    Returns:
        One :class:`ConvChoice` per layer chosen, in module order (also logged).
    """
    pending = {name: layer for name, layer in switchable_layers(net) if layer.impl == AUTO}
    if not pending:
        return []
    start = time.perf_counter()
    threads = torch.get_num_threads()
    machine = machine_key(threads)
    path = cache_path(cache_dir, machine) if cache_dir is not None else None
    cached = _read_cache(path) if path is not None else {}
    inputs = _layer_inputs(net, pending, flow_shape, dtype)
    for name in set(pending) - set(inputs):  # a layer the forward does not reach keeps native
        pending.pop(name).impl = "native"
    keys = {name: layer_key(layer, inputs[name], dtype) for name, layer in pending.items()}
    times: dict[str, dict[str, float]] = {}
    for name, layer in pending.items():
        entry = cached.get(keys[name])
        if isinstance(entry, dict) and set(entry.get("ms", {})) == set(layer.candidates()):
            times[name] = {k: float(v) for k, v in entry["ms"].items()}
    measured = [name for name in pending if name not in times]
    generator = torch.Generator().manual_seed(0)
    wall, cpu = time.perf_counter(), time.process_time()
    for name in measured:
        times[name] = time_layer(pending[name], inputs[name], dtype, repeats, generator)
    share = (time.process_time() - cpu) / max(1e-9, (time.perf_counter() - wall) * threads)
    busy = bool(measured) and share < min_cpu_share
    choices = []
    for name, layer in pending.items():
        layer.impl = "native" if busy and name in measured else pick(times[name])
        choices.append(
            ConvChoice(name, keys[name], inputs[name].shape, times[name], layer.impl,
                       name not in measured)
        )  # fmt: skip
    if busy:
        log.warning(
            "model.net.conv_impl=auto: the machine was busy while the convolutions were timed "
            "(this process got %.0f %% of its %d threads' CPU time): the %d layers timed keep "
            "native and nothing is cached; the next run times them again",
            100 * share, threads, len(measured),
        )  # fmt: skip
    elif path is not None and measured:
        new = {keys[n]: {"ms": {k: round(v, 4) for k, v in times[n].items()},
                         "choice": pick(times[n])} for n in measured}  # fmt: skip
        payload = {"machine": machine, "layers": {**cached, **new}}
        try:
            atomic_write_text(path, json.dumps(payload, indent=1, sort_keys=True) + "\n")
        except OSError as err:  # a read-only cache: the choice still applies to this run
            log.warning("conv_impl: could not cache the measured choice in %s (%s)", path, err)
    log.info(
        "model.net.conv_impl=auto: %d convolutions at batch %d, %s, on %s, %d threads: %d "
        "measured, %d cached in %.1f s%s", len(choices), flow_shape[0], _dtype_name(dtype),
        describe_cpu(), threads, len(measured), len(choices) - len(measured),
        time.perf_counter() - start, f" ({path})" if path is not None else "",
    )  # fmt: skip
    for choice in choices:
        log.info("  %s%s", choice.describe(), " (cached)" if choice.cached else "")
    return choices
