"""Regenerate every benchmark table (``make bench``): accuracy, every flow estimator on the test
worlds and the learned flow's training curve (sections of flow_quality.md), throughput, images
to poses (a section of throughput.md), scale-out, data preparation over processes (a section of
scaleout.md), the KITTI flow cache, and on a machine with a CUDA GPU the GPU check.

Runs the scripts one after the other (each needs the whole machine), each in its own process,
and writes ``bench/results/<name>.md``. Extra arguments (``--tiny``, ``--out DIR``,
``--threads N``) are passed to every script. Exits non-zero if any script fails.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import torch

BENCH = Path(__file__).resolve().parent
SCRIPTS = (
    "accuracy.py",
    "flow_estimators.py",  # after accuracy.py: a section of flow_quality.md
    "flow_training.py",  # the learned flow's curve (committed curve.json): a section of it too
    "throughput.py",
    "images_to_poses.py",  # after throughput.py: a section of its file
    "scaleout.py",
    "data_preparation.py",  # after scaleout.py: a section of its file
    "flow_cache.py",
)
#: Scripts that need a CUDA device: run only where one is (gpu_check.py's CPU form is a test,
#: tests/test_gpu_path.py; `make gpu-check` installs what it needs and runs it).
GPU_SCRIPTS = ("gpu_check.py",)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    start = time.perf_counter()
    failed = []
    scripts = SCRIPTS + (GPU_SCRIPTS if torch.cuda.is_available() else ())
    for script in scripts:
        t0 = time.perf_counter()
        print(f"== {script} {' '.join(args)}", flush=True)
        code = subprocess.run([sys.executable, str(BENCH / script), *args], check=False).returncode
        print(f"== {script}: exit {code} after {time.perf_counter() - t0:.0f} s", flush=True)
        if code:
            failed.append(script)
    print(f"== all benchmarks: {time.perf_counter() - start:.0f} s", flush=True)
    if failed:
        print(f"error: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
