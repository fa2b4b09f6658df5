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


def quick_start_wall(tiny: bool, threads: int) -> list[list[str]]:
    """Wall time of ``python -m mfg_lightning.train`` (the quick start; ``debug=tiny`` when
    ``tiny``) for each of :data:`RUNS`, each with its training time, the precision ``auto``
    chose and its test metrics: table rows."""
    from omegaconf import OmegaConf

    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (label, (extra, cache)) in enumerate(RUNS.items()):
            run_dir = Path(tmp) / f"run{i}"
            cmd = [
                sys.executable, "-m", "mfg_lightning.train", f"hydra.run.dir={run_dir}",
                f"paths.cache_dir={tmp}/cache-{cache}", *(["debug=tiny"] if tiny else []), *extra,
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
            precision = OmegaConf.load(run_dir / "config.yaml").trainer.precision
            results.append((label, wall, result, precision))
    before = results[0][1]
    return [
        [label, fmt(wall, 1), fmt(before / wall, 2), fmt(result["train_seconds"], 1), precision,
         fmt(result["metrics"]["test/ate"], 5), fmt(result["metrics"]["test/rpe_rot"], 6)]
        for label, wall, result, precision in results
    ]  # fmt: skip


def section(args: argparse.Namespace) -> Path:
    """:func:`quick_start_wall` as a section of its own, one per instruction set torch's kernels
    run (its marker and heading name it, and an instruction-set cap); returns the path."""
    caps = isa_caps()
    capability = torch.backends.cpu.get_cpu_capability()
    report = throughput_report(args.out)
    imitated = ", ".join(f"`{k}={v}`" for k, v in caps.items())
    report.add(
        "`python -m mfg_lightning.train`" + (" debug=tiny" if args.tiny else "")
        + f" (training, validation, test) with torch's kernels at {capability}"
        + (f", capped by {imitated}: an imitation of that machine on this one (its instruction "
           "set, not its cores or caches)" if caps else "")
        + ":\n\n"
        + markdown_table(
            ["run", "wall time (s)", "speed-up", "training (s)", "precision (`auto`)",
             "test ATE (m)", "test RPE rot (rad)"],
            quick_start_wall(args.tiny, torch.get_num_threads()),
        )
        + "\nOne run each, one after the other. The cache hands out the generated samples bit "
        "for bit (tests/test_sample_cache.py), and the device-resident split the same batches in "
        "the same order (tests/test_device_resident.py): the test metrics differ only by the "
        "training's own run-to-run variation. The device-resident runs read the whole training "
        "split before their first step (on a CPU the device is the host's memory), where the "
        "others render the first epoch while they train."
    )  # fmt: skip
    marker = f"quick-start-{capability.lower()}" + ("-capped" if caps else "")
    heading = f"The quick start at {capability}" + (" (imitated)" if caps else "")
    return report.write_section(marker, heading)
