"""7. The convolutions' implementations (``model.net.conv_impl``,
:mod:`mfg_lightning.models.conv`): each layer's forward + backward as native / im2col /
channels-last at the training batch, in float32 (and bfloat16 under autocast where the CPU has it
natively), the one ``auto`` picks, and the training step with ``auto``'s choice against native
(bare loop, interleaved). A marked section of throughput.md of its own: ``--convolutions``
reruns only it."""

from __future__ import annotations

import argparse
import statistics
from functools import partial
from pathlib import Path
from typing import Any

import torch
from _common import cpu_description, fmt, markdown_table, ratio_cell

from .measure import build_model, interleaved, make_batches, render, throughput_report
from .training import bare_rate

#: The marker of this section's block in throughput.md (:meth:`Report.write_section`).
CONV_MARKER = "conv-impl"
LAYER_HEADER = [
    "layer (C_in→C_out, kernel / stride)",
    "map (in → out)",
    "dtype",
    "native (ms)",
    "im2col (ms)",
    "channels-last (ms)",
    "chosen",
    "native / chosen",
]
STEP_HEADER = [
    "batch",
    "dtype",
    "native (samples/s)",
    "auto's choice (samples/s)",
    "auto / native (range)",
]


def with_conv_impl(overrides: list[str], impl: str) -> list[str]:
    """``overrides`` with ``model.net.conv_impl=<impl>`` in place of any earlier value."""
    return [o for o in overrides if not o.startswith("model.net.conv_impl=")] + [
        f"model.net.conv_impl={impl}"
    ]


def conv_layer_rows(
    overrides: list[str], shape: tuple[int, ...], dtype: torch.dtype, rounds: int
) -> tuple[list[list[str]], dict[str, str]]:
    """Every convolution timed alone under each implementation, as a training run's first
    measurement of the machine times it (:func:`mfg_lightning.run.machine_profile.
    measure_convolutions`; nothing cached): the table rows (a total row last) and the choice,
    layer name → implementation."""
    from mfg_lightning.models.conv import CONV_IMPLS, layer_inputs, switchable_layers
    from mfg_lightning.run.machine_profile import measure_convolutions

    model, _ = build_model(with_conv_impl(overrides, "native"))
    net = model.net.train()
    layers = dict(switchable_layers(net))
    inputs = layer_inputs(net, layers, shape, dtype)
    measured = measure_convolutions(net, shape, dtype, rounds)
    rows, totals = [], dict.fromkeys([*CONV_IMPLS, "chosen"], 0.0)
    for name, entry in measured.items():
        conv, ms, choice = layers[name], entry["ms"], entry["choice"]
        (k, _), (s, _), (p, _) = conv.kernel_size, conv.stride, conv.padding
        h, w = inputs[name].shape[-2:]
        out = f"{(h + 2 * p - k) // s + 1}×{(w + 2 * p - k) // s + 1}"
        times = [fmt(ms[i], 2) if i in ms else "-" for i in CONV_IMPLS]
        for impl in CONV_IMPLS:
            totals[impl] += ms.get(impl, float("nan"))
        totals["chosen"] += ms[choice]
        rows.append(
            [f"`{name}` {conv.in_channels}→{conv.out_channels}, {k}×{k} / {s}",
             f"{h}×{w} → {out}", str(dtype).removeprefix("torch."), *times, choice,
             fmt(ms["native"] / ms[choice], 2)]
        )  # fmt: skip
    rows.append(
        ["all convolutions", "", str(dtype).removeprefix("torch."),
         *(fmt(totals[i], 2) for i in CONV_IMPLS), "per layer",
         fmt(totals["native"] / totals["chosen"], 2)]
    )  # fmt: skip
    return rows, {name: entry["choice"] for name, entry in measured.items()}


def section(
    args: argparse.Namespace, base: list[str], cfg: Any, samples: list[dict] | None = None
) -> Path:
    """Each layer timed alone (native, im2col, channels-last) at the training batch in every
    dtype training may compute in on this CPU, what ``model.net.conv_impl=auto`` picks, and the
    bare training step with that choice against all native. Written as its own section of
    throughput.md (the rest kept); returns its path."""
    from mfg_lightning.run.run_choices import needs_bf16

    batch_size = 4 if args.tiny else int(cfg.dataset.batch_size)
    if samples is None:
        samples = render(cfg, 2 * batch_size)
    batches = make_batches(samples, batch_size)
    height, width = int(cfg.dataset.height), int(cfg.dataset.width)
    dtypes = [torch.float32]
    if needs_bf16("bf16-mixed"):
        dtypes.append(torch.bfloat16)
    report = throughput_report(args.out)
    report.add(
        f"CPU: {cpu_description()}; torch threads: {torch.get_num_threads()}. MFG "
        f"{height} × {width}, M = {cfg.model.net.hidden_units}, batch {batch_size} (the "
        "training batch)"
        + ("" if len(dtypes) > 1 else "; bfloat16 not measured: this CPU lacks native bfloat16 "
           "(AVX512-BF16, AMX), so bf16-mixed training chooses for float32 only")
        + "."
    )  # fmt: skip
    rows, steps = [], []
    native = with_conv_impl(base, "native")
    for dtype in dtypes:
        layer_rows, choice = conv_layer_rows(
            base, (batch_size, 2, height, width), dtype, args.conv_repeats
        )
        rows += layer_rows
        bf16 = dtype == torch.bfloat16
        rate = partial(bare_rate, native, batches, args.warmup, args.conv_steps, autocast=bf16)
        runs = interleaved({"native": rate, "auto": partial(rate, conv_impls=choice)}, args.repeats)
        pairs = [a / n for a, n in zip(runs["auto"], runs["native"], strict=True)]
        steps.append(
            [batch_size, str(dtype).removeprefix("torch."),
             fmt(statistics.median(runs["native"]), 1), fmt(statistics.median(runs["auto"]), 1),
             ratio_cell(pairs)]
        )  # fmt: skip
    report.add(
        markdown_table(LAYER_HEADER, rows)
        + f"\nEach convolution alone, forward + backward (the weight gradient, and the input "
        "gradient except for the first layer's, the flow), on a random input of the shape and "
        "dtype it gets in the training step, timed as a run's first measurement of the machine "
        f"times it (`python -m mfg_lightning.measure`): {args.conv_repeats} rounds after one "
        "warm-up, the three interleaved in an order rotated each round, the best of each (a "
        "candidate over 2× native's first round is not timed again); bfloat16: the forward "
        "under CPU autocast. The input is NCHW; an implementation's own copies (channels-last: "
        "the input to NHWC; im2col: the padded input and the gathered rows) are timed with it. "
        "*Chosen*: native unless another is over 5 % faster at its best and faster in every "
        "round; `native / chosen`: the layer's speed-up."
    )
    report.add(
        "Training step with the chosen implementations against native:\n\n"
        + markdown_table(STEP_HEADER, steps)
        + f"\nThe bare training loop (section 1: the network, loss and fused Adam; bfloat16: "
        f"the encoder under autocast), {args.warmup} warm-up then {args.conv_steps} steps per "
        f"rate, {args.repeats} interleaved repeats, medians; the ratio of each back-to-back "
        "pair, then their median (range)."
    )
    return report.write_section(CONV_MARKER, "Convolution implementations per layer")
