"""6. The candidate speed-ups of the training step, in the bare loop: fused Adam (adopted),
channels-last, the first convolution (2 input channels) in float32 or padded to 8 channels,
``torch.compile``."""

from __future__ import annotations

from functools import partial
from typing import Any

from _common import fmt, markdown_table

from .measure import Run, make_batches, median_of
from .training import bare_rate

#: The optimiser settings compared: the default build and the faster one.
VARIANTS = {
    "before (for-loop Adam)": ["++model.optimizer.fused=false"],
    "after (fused Adam)": ["++model.optimizer.fused=true"],
}
FUSED = VARIANTS["after (fused Adam)"]
#: Each candidate: its row label → (overrides, options of the bare step).
CANDIDATES: dict[str, tuple[list[str], dict[str, Any]]] = {
    "float32, for-loop Adam (before)": (VARIANTS["before (for-loop Adam)"], {}),
    "float32, fused Adam (after, the default)": (FUSED, {}),
    "float32 + channels-last": (FUSED, {"channels_last": True}),
    "bf16": (FUSED, {"autocast": True}),
    "bf16 + channels-last": (FUSED, {"autocast": True, "channels_last": True}),
    "bf16 + first conv in float32": (FUSED, {"autocast": True, "first_conv": "fp32"}),
    "bf16 + first conv's input padded to 8 channels": (
        FUSED,
        {"autocast": True, "first_conv": "pad8"},
    ),
}


def candidate_rates(run: Run, batch_size: int, steps: int) -> dict[str, float]:
    """Every candidate's samples/s at ``batch_size`` (medians of interleaved repeats), and
    ``torch.compile``'s at the largest batch unless ``--no-compile``."""
    args = run.args
    batches = make_batches(run.samples, batch_size)
    rates = median_of(
        {
            name: partial(bare_rate, run.base + ov, batches, args.warmup, steps, **opt)
            for name, (ov, opt) in CANDIDATES.items()
        },
        args.candidate_repeats,
    )
    if not args.no_compile and batch_size == run.largest:
        # Once: every build compiles anew (tens of seconds), during its first steps, which
        # are left out of the rate as warm-up.
        for name, opt in (
            ("float32 + torch.compile(net)", {}),
            ("bf16 + torch.compile(net)", {"autocast": True}),
        ):
            rates[name] = bare_rate(
                run.base + FUSED, batches, args.warmup + 10, steps, compile_net=True, **opt
            )
    return rates


def section(run: Run) -> None:
    """Measure :func:`candidate_rates` at every batch size and add the table."""
    rows = []
    for batch_size, steps in run.sizes:
        rates = candidate_rates(run, batch_size, steps)
        ref = rates["float32, fused Adam (after, the default)"]
        ref_bf16 = rates["bf16"]
        for name, r in rates.items():
            rel = fmt(r / ref_bf16, 2) if name.startswith("bf16") else "-"
            rows.append([batch_size, name, fmt(r, 1), fmt(r / ref, 2), rel])
    run.report.add(
        "## Candidate speed-ups of the training step (bare loop)\n\n"
        + markdown_table(["batch", "step", "samples/s", "× float32 fused", "× bf16"], rows)
        + "\n`torch.compile` is timed after its compilation (excluded). The first-conv "
        "candidates are patched onto the network in the bare loop only (the same numbers: "
        "float32 is more precise, zero-padded channels add zeros)."
    )
