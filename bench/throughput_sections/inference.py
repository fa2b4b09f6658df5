"""2. Inference: flow → (t, ω) (``predict_motion``) against the network's bare forward, in
frames per second at every batch size. Target: the recovery adds at most 10 %."""

from __future__ import annotations

import statistics
import time

import torch
from _common import fmt, markdown_table

from .measure import Run, build_model, make_batches


def inference_rates(
    overrides: list[str], batches: list[dict], steps: int, repeats: int
) -> dict[str, float]:
    """Frames per second of the bare network forward (``forward``) and of flow → (t, ω)
    (``pose``).

    The two alternate in short chunks (many more than ``repeats``), and each keeps the median
    chunk: a load spike on a shared machine hits both alike instead of one of them.
    """
    from mfg_lightning.core import geometry

    model, _ = build_model(overrides)
    model.eval()
    batch = batches[0]
    flow, K = batch["flow"], batch["intrinsics"]
    calls = {
        "forward": lambda: model.net(flow),
        "pose": lambda: model.predict_motion(flow, K),
    }
    chunk = max(2, steps // 5)
    rates: dict[str, list[float]] = {k: [] for k in calls}
    with torch.inference_mode():
        for fn in calls.values():
            fn()
        geometry.recover_motion(*model.net(flow)[:2], K)
        for _ in range(max(5, 5 * repeats)):
            for name, fn in calls.items():
                start = time.perf_counter()
                for _ in range(chunk):
                    fn()
                rates[name].append(chunk * flow.shape[0] / (time.perf_counter() - start))
    return {k: statistics.median(v) for k, v in rates.items()}


def section(run: Run) -> None:
    """Measure :func:`inference_rates` at every batch size and add the table."""
    rows = []
    for batch_size, steps in run.sizes:
        batches = make_batches(run.samples, batch_size)
        r = inference_rates(run.base, batches, max(steps, 10), run.args.candidate_repeats)
        added = f"{100 * (r['forward'] / r['pose'] - 1):+.1f} %"
        rows.append([batch_size, fmt(r["forward"], 1), fmt(r["pose"], 1), added])
    run.report.add(
        "## Inference: flow → (t, ω) against the bare forward (target ≤ +10 %)\n\n"
        + markdown_table(
            ["batch", "forward (frames/s)", "flow → (t, ω) (frames/s)", "time added"], rows
        )
        + "\n`predict_motion` = `MFG.forward` + `geometry.recover_motion` (cached "
        "pseudo-inverses), `torch.inference_mode`, float32."
    )
