"""5. Where the training step's time goes: ``torch.profiler`` per operator of the bare step under
both precisions, every convolution and decoder timed alone (GFLOP/s, fraction of its dtype's
peak), and what caps bf16-mixed's speed-up."""

from __future__ import annotations

import statistics
import time
from functools import partial

import torch
from _common import fmt, markdown_table

from .gemm_peak import Peaks
from .lightning_vs_bare import TrainingRates, default_kernels, kernel_overrides
from .measure import PRECISIONS, Run, build_model, make_batches
from .training import InMemory, bare_step_fn

#: A per-layer row: (label, implementation, forward ms, backward ms, GFLOP/s of forward +
#: backward); the implementation is ``model.net.conv_impl``'s for a convolution, "" otherwise.
KernelRow = tuple[str, str, float, float, float]


def profile_step(
    overrides: list[str], batches: list[dict], steps: int, rows: int = 8, **options: bool
) -> list[tuple[str, float, float]]:
    """The bare step's most expensive operators: (name, ms per step, share of the step)."""
    from torch.profiler import ProfilerActivity, profile

    model, _ = build_model(overrides)
    step = bare_step_fn(model, **options)
    for batch in InMemory(batches, 3):
        step(batch)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for batch in InMemory(batches, steps):
            step(batch)
    events = [e for e in prof.key_averages() if e.self_cpu_time_total > 0]
    total = sum(e.self_cpu_time_total for e in events)
    top = sorted(events, key=lambda e: -e.self_cpu_time_total)[:rows]
    return [
        (e.key, e.self_cpu_time_total / 1e3 / steps, e.self_cpu_time_total / total) for e in top
    ]


def layer_kernels(overrides: list[str], batch: dict, bf16: bool, repeats: int) -> list[KernelRow]:
    """Every convolution and decoder of the network on its own, on the inputs it gets in the
    step: (layer, forward ms, backward ms, GFLOP/s of forward + backward). Under ``bf16`` the
    convolutions run under bf16 autocast and the decoders in float32, as in the module."""
    from torch import nn
    from torch.utils.flop_counter import FlopCounterMode

    model, _ = build_model(overrides)
    net = model.net.train()
    layers = [(n, m) for n, m in net.named_modules() if isinstance(m, nn.Conv2d | nn.Linear)]
    inputs: dict[str, torch.Tensor] = {}

    def keep(mod, inp, out, name: str) -> None:
        inputs.setdefault(name, inp[0].detach().clone())

    hooks = [m.register_forward_hook(partial(keep, name=name)) for name, m in layers]
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        net(batch["flow"])
    for h in hooks:
        h.remove()
    rows = []
    for i, (name, m) in enumerate(layers):
        # The flow needs no gradient; every later input does (the step back-propagates it).
        x = inputs[name].clone().requires_grad_(i > 0)
        autocast = bf16 and isinstance(m, nn.Conv2d)

        def forward(m=m, x=x, autocast=autocast):
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
                return m(x)

        with FlopCounterMode(display=False) as fc:
            y = forward()
            y.backward(torch.ones_like(y))
        flops = fc.get_total_flops()
        t_fwd, t_bwd = [], []
        for _ in range(repeats):
            start = time.perf_counter()
            y = forward()
            mid = time.perf_counter()
            y.backward(torch.ones_like(y))
            t_fwd.append(mid - start)
            t_bwd.append(time.perf_counter() - mid)
        f, b = statistics.median(t_fwd), statistics.median(t_bwd)
        # Conv2d for every convolution, SwitchableConv2d included
        kind = "Conv2d" if isinstance(m, nn.Conv2d) else type(m).__name__
        label = f"{name} {kind} {tuple(m.weight.shape)} in {tuple(x.shape[1:])}"
        impl = str(getattr(m, "impl", "")) if isinstance(m, nn.Conv2d) else ""
        rows.append((label, impl, 1e3 * f, 1e3 * b, flops / (f + b) / 1e9))
    return rows


def bf16_bound(
    step_ms: dict[str, float],
    kernels: dict[str, list[KernelRow]],
    conv_flops: float,
    batch_size: int,
    bf16_peak: float,
) -> str:
    """What caps bf16-mixed's speed-up: the step split into its convolutions, its decoders and
    the rest (the step's time minus the layers', from the per-layer table), and the speed-up
    the step would have with every convolution at the bf16 GEMM peak and the rest as measured.
    """
    parts = {}
    for name, rows in kernels.items():
        conv = sum(f + b for label, _, f, b, _ in rows if "Conv2d" in label)
        dec = sum(f + b for label, _, f, b, _ in rows if "Linear" in label)
        parts[name] = (conv, dec, step_ms[name] - conv - dec)
    conv32, dec32, rest32 = parts["float32"]
    conv16, dec16, rest16 = parts["bf16-mixed"]
    title = f"## What caps bf16-mixed, batch {batch_size}\n\n"
    if min(rest32, rest16) <= 0:
        # The layers alone took longer than the step they are part of: the two were measured
        # under different load (or the isolated layers miss what the step keeps warm), so the
        # remainder, and any bound built on it, would be an artefact of the measurement.
        return title + (
            f"Not computed in this run: the layers timed alone add up to "
            f"{fmt(conv32 + dec32, 1)} ms (float32) and {fmt(conv16 + dec16, 1)} ms (bf16-mixed), "
            f"against whole Lightning steps of {fmt(step_ms['float32'], 1)} and "
            f"{fmt(step_ms['bf16-mixed'], 1)} ms, so the rest of the step would come out "
            "negative: the layers timed one by one do not add up to the step they are part of "
            "(each alone pays its own cache misses and the load of its moment)."
        )
    at_peak = 1e3 * conv_flops * batch_size / 1e9 / bf16_peak
    if at_peak >= conv16:
        # The convolutions ran at or above the measured peak: that peak is no ceiling, and a
        # bound built on it would be below what was measured.
        return title + (
            f"Not computed in this run: the bf16 convolutions took {fmt(conv16, 1)} ms, no more "
            f"than their FLOPs at the measured bfloat16 GEMM peak ({fmt(bf16_peak, 0)} GFLOP/s: "
            f"{fmt(at_peak, 1)} ms), so that peak is not this machine's ceiling."
        )
    bound = step_ms["float32"] / (at_peak + dec16 + rest16)
    worst = max(kernels["bf16-mixed"], key=lambda r: r[2] + r[3])
    share = (worst[2] + worst[3]) / step_ms["bf16-mixed"]
    rows = [
        ["convolutions", fmt(conv32, 1), fmt(conv16, 1), fmt(at_peak, 1)],
        ["the two decoders (float32 in both)", fmt(dec32, 1), fmt(dec16, 1), fmt(dec16, 1)],
        ["the rest (loss, geometry, Adam, casts, Lightning)", fmt(rest32, 1), fmt(rest16, 1),
         fmt(rest16, 1)],
        ["the step (Lightning)", fmt(step_ms["float32"], 1), fmt(step_ms["bf16-mixed"], 1),
         fmt(at_peak + dec16 + rest16, 1)],
    ]  # fmt: skip
    return (
        title
        + markdown_table(
            ["ms / step", "float32", "bf16-mixed", "bf16, convolutions at the bf16 GEMM peak"],
            rows,
        )
        + f"\nWith every convolution at the bfloat16 GEMM peak ({fmt(bf16_peak, 0)} GFLOP/s) and "
        f"the rest as measured, bf16-mixed would be at most **{bound:.2f}×** float32 at batch "
        f"{batch_size}; measured, its convolutions run at "
        f"{100 * at_peak / conv16:.0f} % of that peak on average. The most expensive kernel is "
        f"`{worst[0]}` as {worst[1]} ({100 * share:.0f} % of the bf16 step, at "
        f"{100 * worst[4] / bf16_peak:.0f} % of the bf16 peak). The decoders stay float32 by "
        "design (the fields must come out in float32: recovery from bf16-rounded fields errs "
        "up to 5e-4 m)."
    )


def kernel_rows(kernels: dict[str, list[KernelRow]], peaks: Peaks) -> list[list[str]]:
    """The per-layer table: float32 and bf16-mixed side by side, each against its own peak."""
    f32_peak, bf16_peak = peaks.gflops["float32"], peaks.gflops["bf16-mixed"]
    return [
        [f"`{label}`", f"{i32 or '-'} / {i16 or '-'}", f"{fmt(f32, 2)} / {fmt(b32, 2)}",
         f"{fmt(g32, 0)} ({100 * g32 / f32_peak:.0f} %)", f"{fmt(f16, 2)} / {fmt(b16, 2)}",
         f"{fmt(g16, 0)} ({100 * g16 / bf16_peak:.0f} %)", fmt((f32 + b32) / (f16 + b16), 2)]
        for (label, i32, f32, b32, g32), (_, i16, f16, b16, g16) in zip(
            kernels["float32"], kernels["bf16-mixed"], strict=True
        )
    ]  # fmt: skip


def section(run: Run, peaks: Peaks, rates: TrainingRates) -> None:
    """Profile the bare step at the largest batch under both precisions, time every layer
    alone, and bound bf16-mixed with the Lightning step times of ``rates``."""
    largest, report = run.largest, run.report
    batches = make_batches(run.samples, largest)
    steps = dict(run.sizes)[largest]
    # each precision on the convolutions a training run computes with (as section 1's steps)
    chosen = default_kernels(run, largest)
    base = {name: kernel_overrides(run, chosen, name) for name in PRECISIONS}
    for name, precision in PRECISIONS.items():
        prof = profile_step(
            base[name], batches, max(3, steps // 3), rows=12, autocast=precision != "32-true"
        )
        report.add(
            f"## Profile of the bare training step, batch {largest}, {name}\n\n"
            + markdown_table(
                ["operator", "ms / step (self)", "share"],
                [[op, fmt(ms, 2), f"{100 * share:.0f} %"] for op, ms, share in prof],
            )
        )
    repeats = max(3, run.args.repeats)
    kernels = {
        name: layer_kernels(base[name], batches[0], precision != "32-true", repeats)
        for name, precision in PRECISIONS.items()
    }
    report.add(
        f"## Per-layer kernels, batch {largest}\n\n"
        + markdown_table(
            [
                "layer (weight, input C × H × W)",
                "kernel fp32 / bf16",
                "fp32 fwd / bwd (ms)",
                "fp32 GFLOP/s (of fp32 peak)",
                "bf16 fwd / bwd (ms)",
                "bf16 GFLOP/s (of bf16 peak)",
                "bf16 speed-up",
            ],
            kernel_rows(kernels, peaks),
        )
        + "\nEach layer alone on the input it gets in the step (captured by a forward hook), "
        "its forward and its backward (input and weight gradients; the first layer's input, "
        "the flow, needs none) timed separately, medians; each precision on the convolutions a "
        "training run computes with (*kernel*: this machine's measurement, as in section 1); "
        "bf16: the convolutions under bf16 autocast (including the casts autocast inserts), the "
        "decoders in float32 as in the module. GFLOP/s: FlopCounterMode's count of forward + "
        "backward over their time. *bf16 speed-up*: of the layer as each precision computes it."
    )
    step_ms = {
        name: 1e3 * largest / statistics.median(rates[(largest, name)][0]) for name in PRECISIONS
    }
    conv_flops = peaks.flops - peaks.decoders
    report.add(bf16_bound(step_ms, kernels, conv_flops, largest, peaks.gflops["bf16-mixed"]))
