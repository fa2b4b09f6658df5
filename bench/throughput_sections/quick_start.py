"""The quick start, ``python -m mfg_lightning.train`` as the README runs it, without and with the
sample cache, and with the training split held in memory (``dataset.device_resident``): wall
time, training time, the precision ``auto`` chose and the test metrics, in a marked section of
throughput.md per instruction set torch's kernels run
(:func:`~mfg_lightning.core.machine.isa_caps`: an imitated machine is said in the heading).
``--quick-start`` runs only it."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from _common import fmt, markdown_table

from mfg_lightning.core.machine import isa_caps

from .measure import UNCACHED_SAMPLES, throughput_report

#: The runs, one after the other: label → (overrides, the cache directory's name; the third and
#: the fifth run share the second's, whose disk tier they find filled).
RUNS = {
    "without the cache (`memory_mb=0 disk=false prefetch=none`)": (UNCACHED_SAMPLES, "a"),
    "the defaults, empty cache": ([], "b"),
    "the defaults, disk tier filled by the run before": ([], "b"),
    "device-resident (`+dataset.device_resident=true`), empty cache": (
        ["+dataset.device_resident=true"],
        "c",
    ),
    "device-resident, disk tier filled by the runs before": (
        ["+dataset.device_resident=true"],
        "b",
    ),
}


def _train(
    run_dir: Path, cache: Path, tmp: str, tiny: bool, threads: int, extra: list[str]
) -> tuple[float, dict, str]:
    """One ``python -m mfg_lightning.train`` into ``run_dir``: wall seconds, its metrics.json
    and the precision ``auto`` chose."""
    from omegaconf import OmegaConf

    cmd = [
        sys.executable, "-m", "mfg_lightning.train", f"hydra.run.dir={run_dir}",
        f"paths.cache_dir={cache}", *(["debug=tiny"] if tiny else []), *extra,
    ]  # fmt: skip
    start = time.perf_counter()
    proc = subprocess.run(
        cmd, cwd=tmp, env={**os.environ, "OMP_NUM_THREADS": str(threads)},
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {proc.stderr[-3000:]}")
    result = json.loads((run_dir / "metrics.json").read_text())
    return wall, result, OmegaConf.load(run_dir / "config.yaml").trainer.precision


def quick_start_wall(tiny: bool, threads: int) -> tuple[list[list[str]], float, list[list[str]]]:
    """Wall time of ``python -m mfg_lightning.train`` (the quick start; ``debug=tiny`` when
    ``tiny``) for each of :data:`RUNS`, each with its training time, the precision ``auto``
    chose and its test metrics (table rows); and the fit's and test's profile (Lightning's
    ``SimpleProfiler``) of a last run of the defaults: the actions that take the most time."""
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (label, (extra, cache)) in enumerate(RUNS.items()):
            cache_dir = Path(tmp) / f"cache-{cache}"
            wall, result, precision = _train(Path(tmp) / f"run{i}", cache_dir, tmp, tiny,
                                             threads, extra)  # fmt: skip
            results.append((label, wall, result, precision))
        profiled = Path(tmp) / "profiled"
        profiler = [
            "+trainer.profiler._target_=lightning.pytorch.profilers.SimpleProfiler",
            f"+trainer.profiler.dirpath={profiled}",
            "+trainer.profiler.filename=profile",
        ]
        wall, _, _ = _train(profiled, Path(tmp) / "cache-b", tmp, tiny, threads, profiler)
        actions = profile_rows(profiled, wall)
    before = results[0][1]
    rows = [
        [label, fmt(wall, 1), fmt(before / wall, 2), fmt(result["train_seconds"], 1), precision,
         fmt(result["metrics"]["test/ate"], 5), fmt(result["metrics"]["test/rpe_rot"], 6)]
        for label, wall, result, precision in results
    ]  # fmt: skip
    return rows, actions


def action_name(name: str) -> str:
    """A profiled action without the callback's state key (``LastCheckpoint{'path': ...}``),
    which names the run's temporary directory."""
    import re

    return re.sub(r"\{.*\}", "", name)


def profile_rows(run_dir: Path, wall: float, top: int = 14) -> list[list[str]]:
    """The ``top`` actions of the profiled run's fit and test by total time (Lightning's
    ``SimpleProfiler`` reports, ``fit-profile.txt`` and ``test-profile.txt``; they nest: a
    training batch holds its step, its backward and its optimiser step), each with its share of
    the run's wall time."""
    # The profiler keeps its records across stages: the test's report repeats the fit's
    # actions, so the test's own time is its report's total less the fit's.
    reports: dict[str, dict[str, float]] = {}
    for stage in ("fit", "test"):
        path = run_dir / f"{stage}-profile.txt"
        actions = reports.setdefault(stage, {})
        for line in path.read_text().splitlines() if path.is_file() else []:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if len(cells) == 5 and cells[0] not in ("Action", "Total"):
                try:
                    actions[cells[0]] = float(cells[3])
                except ValueError:
                    continue
    fit, test = reports["fit"], reports["test"]
    totals = {f"fit: {k}": v for k, v in fit.items()}
    for name, seconds in test.items():
        if seconds - fit.get(name, 0.0) > 1e-3:
            totals[f"test: {name}"] = seconds - fit.get(name, 0.0)
    ranked = sorted(totals.items(), key=lambda kv: -kv[1])[:top]
    rows = [[f"`{action_name(name)}`", fmt(seconds, 1), f"{100 * seconds / wall:.0f} %"]
            for name, seconds in ranked]  # fmt: skip
    return rows


def limit_rows(tiny: bool, precision: str, wall: float, train_seconds: float) -> list[list[str]]:
    """The quick start's work against the machine's limit: the network's FLOPs for every sample
    it trains on (forward + backward, ``trainer.max_steps × dataset.batch_size``) and evaluates
    (forward: each validation and the test) over the measured GEMM peak in the precision
    ``auto`` chose, beside the measured times."""
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    from .gemm_peak import gemm_peak, step_flops
    from .measure import make_batches, render

    overrides = ["paths.output_dir=.", *(["debug=tiny"] if tiny else [])]
    cfg = compose("train", overrides)
    batch = make_batches(render(cfg, int(cfg.dataset.batch_size)), int(cfg.dataset.batch_size))[0]
    forward, backward, _ = step_flops(overrides, batch)
    datamodule = instantiate(cfg.dataset)
    steps, every = int(cfg.trainer.max_steps), int(cfg.trainer.val_check_interval)
    trained = steps * int(cfg.dataset.batch_size)
    evaluated = (steps // every) * len(datamodule.dataset("val")) + len(datamodule.dataset("test"))
    dtype = torch.bfloat16 if precision == "bf16-mixed" else torch.float32
    peak = gemm_peak(dtype, 2048, 3)  # GFLOP/s
    limit = (trained * (forward + backward) + evaluated * forward) / 1e9 / peak
    return [
        ["samples trained (forward + backward)", f"{trained:,}",
         fmt((forward + backward) / 1e9, 3)],
        ["samples evaluated (forward)", f"{evaluated:,}", fmt(forward / 1e9, 3)],
        [f"2048² GEMM peak, {str(dtype).removeprefix('torch.')} (GFLOP/s)", fmt(peak, 0), ""],
        ["the limit: all of it at the peak (s)", fmt(limit, 1), ""],
        ["measured: training (s), of it", fmt(train_seconds, 1),
         fmt(train_seconds / limit, 1) + "×"],
        ["measured: wall time (s)", fmt(wall, 1), fmt(wall / limit, 1) + "×"],
    ]  # fmt: skip


def section(args: argparse.Namespace) -> Path:
    """:func:`quick_start_wall` as a section of its own, one per instruction set torch's kernels
    run (its marker and heading name it, and an instruction-set cap), with the limit
    (:func:`limit_rows`) and the profile of a run of the defaults; returns the path."""
    caps = isa_caps()
    capability = torch.backends.cpu.get_cpu_capability()
    report = throughput_report(args.out)
    imitated = ", ".join(f"`{k}={v}`" for k, v in caps.items())
    rows, actions = quick_start_wall(args.tiny, torch.get_num_threads())
    defaults = rows[2]  # the defaults, disk tier filled: what a user's second run is
    limits = limit_rows(args.tiny, defaults[4], float(defaults[1].replace(",", "")),
                        float(defaults[3].replace(",", "")))  # fmt: skip
    report.add(
        "`python -m mfg_lightning.train`" + (" debug=tiny" if args.tiny else "")
        + f" (training, validation, test) with torch's kernels at {capability}"
        + (f", capped by {imitated}: an imitation of that machine on this one (its instruction "
           "set, not its cores or caches)" if caps else "")
        + ":\n\n"
        + markdown_table(
            ["run", "wall time (s)", "speed-up", "training (s)", "precision (`auto`)",
             "test ATE (m)", "test RPE rot (rad)"],
            rows,
        )
        + "\nOne run each, one after the other. The cache hands out the generated samples bit "
        "for bit (tests/test_sample_cache.py), and the device-resident split the same batches in "
        "the same order (tests/test_device_resident.py): the test metrics differ only by the "
        "training's own run-to-run variation. The device-resident runs read the whole training "
        "split before their first step (on a CPU the device is the host's memory), where the "
        "others render the first epoch while they train. Every run read its precision and "
        "kernels from this CPU kind's row of conf/cpu_defaults.yaml."
    )  # fmt: skip
    report.add(
        "Against the limit (the defaults, disk tier filled):\n\n"
        + markdown_table(["", "value", "GFLOP / sample, or × the limit"], limits)
        + "\nFLOPs as section 0 counts them (convolutions and matrix products; element-wise "
        "work, the loss, the geometry and Adam count nothing)."
    )
    report.add(
        "Where the time goes: a further run of the defaults (disk tier filled) under "
        "Lightning's `SimpleProfiler` (`+trainer.profiler=...`), the actions that took the "
        "most, fit and test; they nest (a training batch holds its step, backward and "
        "optimiser step), so the shares do not add up:\n\n"
        + markdown_table(["action", "total (s)", "of the wall time"], actions)
    )
    marker = f"quick-start-{capability.lower()}" + ("-capped" if caps else "")
    heading = f"The quick start at {capability}" + (" (imitated)" if caps else "")
    return report.write_section(marker, heading)
