"""0. The machine's GEMM peak in float32 and bfloat16 and the network's FLOPs per sample: what
every later rate is set against (a fraction of its own dtype's peak)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from _common import fmt, markdown_table

from .measure import Run, build_model, make_batches


def gemm_peak(dtype: torch.dtype, n: int, repeats: int) -> float:
    """GFLOP/s of an ``n × n`` matrix product in ``dtype`` (2 n³ FLOPs; the best of ``repeats``
    timed products of ten, after two warm-up products). The best, not the median: a peak is
    what the machine can do, and load only ever adds time (a median of 3 on 2 shared cores gave
    1,125 GFLOP/s in bfloat16 where a convolution of the same run reached 1,751)."""
    a, b = torch.randn(n, n).to(dtype), torch.randn(n, n).to(dtype)
    for _ in range(2):
        a @ b
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(10):
            a @ b
        times.append((time.perf_counter() - start) / 10)
    return 2 * n**3 / min(times) / 1e9


def step_flops(overrides: list[str], batch: dict) -> tuple[float, float, float]:
    """FLOPs per sample of the network's forward, of its backward, and of the decoders' share
    of both, 2 FLOPs per multiply-add (``torch.utils.flop_counter.FlopCounterMode``:
    convolutions and matrix products, the weight and the input gradients; element-wise work,
    the loss and Adam count nothing)."""
    from torch.utils.flop_counter import FlopCounterMode

    from mfg_lightning.core import geometry

    model, _ = build_model(overrides)
    net, loss_fn = model.net, model.loss_fn
    flow, K = batch["flow"], batch["intrinsics"]
    t, w = geometry.pose_to_motion(batch["pose"])
    v_t = geometry.translational_field(t, K, *flow.shape[-2:])
    v_w = geometry.rotational_field(w, K, *flow.shape[-2:])
    with FlopCounterMode(display=False) as fwd:
        out = net(flow)
    terms = loss_fn(out.v_t, out.v_omega, v_t, v_w, out.hidden)
    with FlopCounterMode(display=False) as bwd:
        terms.total.backward()
    n = flow.shape[0]
    # The decoders analytically: forward, input and weight gradients of two M → 2hw products.
    decoders = 2 * 3 * 2 * net.hidden_units * net.decoder_t.out_features
    return fwd.get_total_flops() / n, bwd.get_total_flops() / n, decoders


@dataclass
class Peaks:
    """The GEMM peaks (GFLOP/s; ``float32`` and ``bf16-mixed``, the bfloat16 product) and the
    network's FLOPs per sample (forward, backward, the decoders' share of both)."""

    gflops: dict[str, float]
    forward: float
    backward: float
    decoders: float

    @property
    def flops(self) -> float:
        """FLOPs per training sample: forward + backward."""
        return self.forward + self.backward

    def fraction(self, rate: float, precision: str) -> str:
        """A table cell: ``rate`` (samples/s) × the FLOPs / the peak of ``precision``'s dtype."""
        return f"{100 * rate * self.flops / 1e9 / self.gflops[precision]:.1f} %"


def section(run: Run) -> Peaks:
    """Time both GEMM peaks, count the FLOPs at the largest batch, add the section."""
    args, n = run.args, 256 if run.args.tiny else 2048
    peaks = Peaks(
        {
            "float32": gemm_peak(torch.float32, n, args.repeats),
            "bf16-mixed": gemm_peak(torch.bfloat16, n, args.repeats),
        },
        *step_flops(run.base, make_batches(run.samples, run.largest)[0]),
    )
    f32, bf16 = peaks.gflops["float32"], peaks.gflops["bf16-mixed"]
    run.report.add(
        "## GEMM peak and the model's FLOPs\n\n"
        + markdown_table(
            ["", "value"],
            [
                [f"{n}² matmul, float32 (GFLOP/s)", fmt(f32, 0)],
                [f"{n}² matmul, bfloat16 (GFLOP/s)", fmt(bf16, 0)],
                ["bfloat16 / float32", fmt(bf16 / f32, 2)],
                ["network forward (GFLOP / sample)", fmt(peaks.forward / 1e9, 3)],
                ["network backward (GFLOP / sample)", fmt(peaks.backward / 1e9, 3)],
                ["of which the two decoders (GFLOP / sample)", fmt(peaks.decoders / 1e9, 3)],
            ],
        )
        + "\nPeaks: the best of timed products in this run (2 n³ FLOPs each). FLOPs: "
        "`torch.utils.flop_counter.FlopCounterMode` around the network's forward and around "
        f"the loss's backward at batch {run.largest}, divided by the batch: convolutions and "
        "matrix products (forward, input and weight gradients; the flow needs no gradient), "
        "nothing for element-wise work, the loss, the upsampling or Adam. A rate's fraction of "
        "the peak below is samples/s × these FLOPs / the peak of its own dtype (bf16-mixed: the "
        "bfloat16 peak, although its decoders run in float32). A fraction above 100 % is a "
        "kernel that outran the 2048² product of its dtype, which is then not that dtype's "
        "ceiling on this CPU (oneDNN's float32 convolutions have done so here)."
    )
    return peaks
