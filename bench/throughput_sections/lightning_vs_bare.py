"""1. Training samples per second through the Lightning Trainer against the bare PyTorch loop,
under ``32-true`` and ``bf16-mixed``, all four interleaved at every batch size, and the two
alternated step by step in one process (the ratio the target is judged on); then bf16-mixed
against float32 from the same repeats."""

from __future__ import annotations

import statistics
from functools import partial

from _common import NOISY, fmt, markdown_table, ratio_cell

from .gemm_peak import Peaks
from .measure import PRECISIONS, Run, interleaved, make_batches, with_overrides
from .training import bare_rate, lightning_rate, paired_steps

#: (batch size, precision label) → the repeats' rates (samples/s): Lightning's, the bare loop's.
TrainingRates = dict[tuple[int, str], tuple[list[float], list[float]]]

HEADER = [
    "batch",
    "precision",
    "Lightning (samples/s)",
    "bare loop (samples/s)",
    "ratio (range)",
    "step-paired ratio (quartiles)",
    "Lightning ms/step",
    "Lightning − bare (ms/step)",
    "Lightning, of GEMM peak",
    "bare, of GEMM peak",
]


def default_kernels(run: Run, batch_size: int) -> dict[str, list[str] | str]:
    """The convolutions a training run at ``batch_size`` computes with by default, per precision
    label: this CPU kind's row of conf/cpu_defaults.yaml
    (:func:`mfg_lightning.run.run_choices.resolve_run_choices`)."""
    import copy

    from mfg_lightning.run.run_choices import resolve_run_choices

    from .measure import _config

    kernels = {}
    for label, precision in (("float32", "32-true"), ("bf16-mixed", "bf16-mixed")):
        cfg = copy.deepcopy(_config(tuple(with_overrides(
            run.base, [f"dataset.batch_size={batch_size}", "model.net.conv_impl=auto",
                       f"trainer.precision={precision}"]))))  # fmt: skip
        resolve_run_choices(cfg)
        impl = cfg.model.net.conv_impl
        kernels[label] = impl if isinstance(impl, str) else list(impl)
    return kernels


def kernel_overrides(run: Run, kernels: dict[str, list[str] | str], name: str) -> list[str]:
    """The run's overrides with precision ``name``'s convolutions of ``kernels``."""
    impl = kernels[name]
    value = impl if isinstance(impl, str) else f"[{','.join(impl)}]"
    return with_overrides(run.base, [f"model.net.conv_impl={value}"])


def step_paired_ratios(run: Run) -> dict[tuple[int, str], list[float]]:
    """Every batch size's and precision's Lightning / bare ratio of each step pair
    (:func:`~throughput_sections.training.paired_steps`: bare time over Lightning time), on
    the convolutions a training run chooses."""
    args, ratios = run.args, {}
    for batch_size, steps in run.sizes:
        batches = make_batches(run.samples, batch_size)
        kernels = default_kernels(run, batch_size)
        for name, precision in PRECISIONS.items():
            pairs = paired_steps(kernel_overrides(run, kernels, name), batches, args.warmup,
                                 steps * args.repeats, precision)  # fmt: skip
            ratios[(batch_size, name)] = [b / lit for lit, b in pairs]
    return ratios


def quartile_cell(ratios: list[float], digits: int = 3) -> str:
    """``median (first–third quartile)`` of per-step ratios."""
    q1, mid, q3 = statistics.quantiles(ratios, n=4)
    return f"{mid:.{digits}f} ({q1:.{digits}f}–{q3:.{digits}f})"


def training_rates(run: Run) -> TrainingRates:
    """Every batch size's four rates (Lightning and bare, float32 and bf16-mixed), interleaved
    ``--repeats`` times, each precision on the convolutions a training run chooses for it."""
    args, rates = run.args, {}
    for batch_size, steps in run.sizes:
        batches = make_batches(run.samples, batch_size)
        kernels = default_kernels(run, batch_size)
        fns = {}
        for name, precision in PRECISIONS.items():
            base = kernel_overrides(run, kernels, name)
            fns[(name, "lightning")] = partial(
                lightning_rate, base, batches, args.warmup, steps, precision
            )
            fns[(name, "bare")] = partial(
                bare_rate, base, batches, args.warmup, steps, autocast=precision != "32-true"
            )
        runs = interleaved(fns, args.repeats)
        for name in PRECISIONS:
            rates[(batch_size, name)] = (runs[(name, "lightning")], runs[(name, "bare")])
    return rates


def section(run: Run, peaks: Peaks) -> TrainingRates:
    """Measure :func:`training_rates` and add both tables; returns the rates."""
    rates, rows = training_rates(run), []
    paired = step_paired_ratios(run)
    for (batch_size, name), (lit, bare) in rates.items():
        r_lit, r_bare = statistics.median(lit), statistics.median(bare)
        # The ratio of each back-to-back pair, then their median: a change of the machine's
        # load between pairs cancels out.
        pairs = [a / b for a, b in zip(lit, bare, strict=True)]
        rows.append(
            [batch_size, name, fmt(r_lit, 1), fmt(r_bare, 1), ratio_cell(pairs),
             quartile_cell(paired[(batch_size, name)]),
             fmt(1e3 * batch_size / r_lit, 1),
             fmt(1e3 * batch_size / r_lit - 1e3 * batch_size / r_bare, 2),
             peaks.fraction(r_lit, name), peaks.fraction(r_bare, name)]
        )  # fmt: skip
    run.report.add(
        "## Training: Lightning Trainer against a bare PyTorch loop (target ≥ 0.95×)\n\n"
        + markdown_table(HEADER, rows)
        + "\nLightning: `lightning.Trainer(precision=...)`, `32-true` or `bf16-mixed`, on the "
        "module's `training_step`; the bare loop: the same network, loss and fused Adam, each "
        "precision on the convolutions a training run chooses for it at that batch (this "
        "machine's measurement, `python -m mfg_lightning.measure`: the defaults' kernels), the "
        "encoder under `torch.autocast('cpu', dtype=torch.bfloat16)` for bf16-mixed (the "
        "decoders leave autocast and run in float32, as in the module). The Trainer runs without "
        "logger, checkpointing or progress bar. What Lightning adds is a fixed cost per step, "
        "whatever the batch: its loop (about 40 hook calls), the optimiser closure and the "
        "result collection of `self.log`, which the module calls only on the logging steps; at "
        "batch 1 that fixed cost is what separates the ratio from 1. *Ratio*: that of each "
        f"back-to-back pair of {run.args.repeats} interleaved repeats, their median (range); "
        f"*noisy*: the range leaves ±{100 * NOISY:.0f} % of the median, here and in every "
        "ratio below. *Step-paired ratio*: the two loops alternated step by step in one "
        "process (after each Lightning step one bare step of a twin model on the same batch; "
        f"{run.args.repeats} × the steps above after the warm-up), the bare step's time over the "
        "Lightning step's of each pair, their median (quartiles): a pair ran milliseconds apart, "
        "so a change of load reaches both. The target is judged on it."
    )
    ratio_rows = []
    for batch_size, _ in run.sizes:
        lit32, bare32 = rates[(batch_size, "float32")]
        lit16, bare16 = rates[(batch_size, "bf16-mixed")]
        pl = [a / b for a, b in zip(lit16, lit32, strict=True)]
        pb = [a / b for a, b in zip(bare16, bare32, strict=True)]
        target = {32: "≥ 2.2", 16: "≥ 1.8"}.get(batch_size, "-")
        ratio_rows.append([batch_size, ratio_cell(pl, 2), ratio_cell(pb, 2), target])
    run.report.add(
        "## bf16-mixed against float32\n\n"
        + markdown_table(
            ["batch", "Lightning bf16 / fp32 (range)", "bare bf16 / fp32 (range)", "target"],
            ratio_rows,
        )
        + "\nThe ratio of each interleaved repeat (float32 and bf16 run back to back), then "
        "their median."
    )
    return rates
