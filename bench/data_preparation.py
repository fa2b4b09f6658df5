"""Data preparation on every core: how does ``flow=dis``'s preparation (rendering the synthetic
worlds, DIS, the cache, the flow quality) scale with the processes it is given?

Measured: ``SyntheticDataModule.prepare_data()``, what a training run with ``flow=dis`` calls
before its first step, on ``--sequences`` procedural training trajectories and as many test
trajectories of ``--frames`` frames each, rendered at ``--render-size`` with DIS ``--preset``,
into an empty cache, once for each process count of ``--processes``
(``dataset.prepare_workers``; 1: in this process, on one thread; more: a pool of
single-threaded spawned processes sharing chunks of at least ``--chunk-pairs`` pairs from every
sequence of both splits, :func:`mfg_lightning.data.rendered_preparation.prepare_pairs`). Where
the largest count exceeds the number of sequences, it is measured once more with every sequence
one chunk: the work shared out by whole sequences, as it was before chunks (with the thread
caps).

Reported per row: pairs/s = pairs / wall time of the whole call (process start-up, rendering,
estimation, writes, the quality and the pictures), the speed-up over 1 process, the scaling
efficiency = speed-up / processes, and the CPU seconds per pair of this process and its finished
workers together (a rise with the processes is contention: memory bandwidth, shared caches,
clock speed; a fall in efficiency beyond it is idle cores).

Every measurement is a stage cached under ``--work`` (a JSON file named by the workload's
settings and the process count): a rerun resumes where an interrupted one stopped, ``--fresh``
measures again. Written as one section of ``<out>/scaleout.md`` between
``<!-- data-preparation:start -->`` and ``<!-- data-preparation:end -->``; ``bench/scaleout.py``
keeps the section when it rewrites the file.

``python bench/data_preparation.py`` (the default workload's 800 pairs take about 2 minutes in one
process of a quiet core, half that in 2, ...: about 3 minutes in all on 2 cores, 5 on 16; it needs
the whole machine); ``--tiny`` for a smoke run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (
    Report,
    add_common_arguments,
    cpu_seconds,
    fmt,
    load_average,
    markdown_table,
)

#: The marker of this script's section in scaleout.md.
MARKER = "data-preparation"
HEADING = "Data preparation (`flow=dis`): pairs per second over processes"
#: ``--tiny``: a model input of the tiny config and a render size the renderer takes.
TINY_INPUT = ("dataset.height=32", "dataset.width=64")


def default_processes(cores: int) -> list[int]:
    """1, 2, then the powers of two below ``cores``, then ``cores``: e.g. 16 → 1 2 4 8 16."""
    counts, n = {1, cores}, 2
    while n < cores:
        counts.add(n)
        n *= 2
    return sorted(counts)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    from mfg_lightning.core.machine import usable_cores
    from mfg_lightning.data.rendered import RENDER_SIZE
    from mfg_lightning.data.rendered_preparation import MIN_CHUNK_PAIRS
    from mfg_lightning.flow.cache import default_cache_dir

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--processes", type=int, nargs="+", default=None,
                   help="process counts (default: 1, 2, the powers of two below the usable "
                   "cores, the usable cores)")  # fmt: skip
    p.add_argument("--sequences", type=int, default=2, help="trajectories per split")
    p.add_argument("--frames", type=int, default=201, help="frames per trajectory")
    p.add_argument("--render-size", default=f"{RENDER_SIZE[0]}x{RENDER_SIZE[1]}", help="HxW")
    p.add_argument("--preset", default="medium", help="DIS preset")
    p.add_argument("--chunk-pairs", type=int, default=MIN_CHUNK_PAIRS,
                   help="dataset.prepare_chunk_pairs: the least pairs of a chunk")  # fmt: skip
    p.add_argument("--work", type=Path, default=default_cache_dir() / "bench-data-preparation",
                   help="where the measurements are cached, and the scratch caches")  # fmt: skip
    p.add_argument("--fresh", action="store_true", help="measure again, ignoring --work")
    add_common_arguments(p, "threads of the 1-process row (default 1, as every worker has)")
    args = p.parse_args(argv)
    if args.tiny:
        args.sequences, args.frames, args.render_size, args.chunk_pairs = 1, 12, "64x128", 2
        args.processes = args.processes or [1, 2]
    args.processes = sorted(set(args.processes or default_processes(usable_cores())))
    try:
        args.height, args.width = (int(v) for v in args.render_size.lower().split("x"))
    except ValueError:
        p.error(f"--render-size: HxW, e.g. 192x512, got {args.render_size!r}")
    # (12 frames: the fewest whose 5 % validation tail has a pair, which prepare_data needs)
    if min(args.processes) < 1 or args.sequences < 1 or args.frames < 12:
        p.error("--processes and --sequences at least 1, --frames at least 12")
    return args


def workload(args: argparse.Namespace) -> dict:
    """The settings that change what is prepared (the stage files' key)."""
    return {
        "sequences": args.sequences,
        "frames": args.frames,
        "render_size": [args.height, args.width],
        "preset": args.preset,
        "tiny": args.tiny,
    }


def overrides(args: argparse.Namespace, cache: Path, processes: int, chunk: int) -> list[str]:
    """The Hydra overrides of the measured data module (``++``: whether or not the config
    lists the key)."""
    return [
        "flow=dis",
        f"flow.preset={args.preset}",
        f"flow.height={args.height}",
        f"flow.width={args.width}",
        "dataset.trajectory=procedural",
        f"dataset.train_sequences={args.sequences}",
        f"dataset.test_sequences={args.sequences}",
        f"dataset.sequence_length={args.frames}",
        f"dataset.cache_dir={cache}",
        f"dataset.prepare_workers={processes}",
        f"dataset.prepare_chunk_pairs={chunk}",
        f"paths.output_dir={cache.parent / 'run'}",
        *(TINY_INPUT if args.tiny else ()),
    ]


def measure(args: argparse.Namespace, processes: int, whole: bool = False) -> dict:
    """One ``prepare_data()`` into an empty cache with ``processes`` processes (``whole``:
    chunks of whole sequences), cached as a stage under ``--work``."""
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    key = hashlib.sha256(json.dumps(workload(args), sort_keys=True).encode()).hexdigest()[:12]
    label = f"{processes}{'-whole' if whole else ''}-{args.chunk_pairs}"
    path = args.work / f"rate-{key}-{label}.json"
    if path.is_file() and not args.fresh:
        try:
            return json.loads(path.read_text())
        except json.JSONDecodeError:  # a torn file: measure again
            pass
    # whole sequences: a chunk as long as a sequence's pairs (frames - 1 at offset 1)
    chunk = args.frames - 1 if whole else args.chunk_pairs
    cache = args.work / "scratch" / "cache"
    shutil.rmtree(cache.parent, ignore_errors=True)
    dm = instantiate(compose("train", overrides(args, cache, processes, chunk)).dataset)
    pairs = sum(len(dm.build_dataset(part)) for part in ("train+val", "test"))
    load_start = load_average()
    cpu_start, start = cpu_seconds(), time.perf_counter()
    dm.prepare_data()
    seconds = time.perf_counter() - start
    result = {
        "processes": processes,
        "whole_sequences": whole,
        "chunk_pairs": chunk,
        "pairs": pairs,
        "seconds": seconds,
        "cpu_seconds": cpu_seconds() - cpu_start,
        "load_start": load_start,
        "load_end": load_average(),
        "workload": workload(args),
    }
    shutil.rmtree(cache.parent, ignore_errors=True)
    from mfg_lightning.core.atomic import atomic_write_text

    atomic_write_text(path, json.dumps(result, indent=2) + "\n")
    print(f"{label}: {pairs} pairs in {seconds:.1f} s ({pairs / seconds:.2f} pairs/s)", flush=True)
    return result


def table(rows: list[dict]) -> str:
    """The scaling table: one row per measurement, speed-up and efficiency against the first
    1-process row (none: against the smallest count, scaled by it)."""
    base = next((r for r in rows if r["processes"] == 1 and not r["whole_sequences"]), rows[0])
    base_rate = base["pairs"] / base["seconds"] / base["processes"]
    out = []
    for r in rows:
        rate = r["pairs"] / r["seconds"]
        speedup = rate / base_rate
        if r["processes"] == 1:
            chunks = "none (this process)"
        elif r["whole_sequences"]:
            chunks = "whole sequences"
        else:
            chunks = f"≥ {r['chunk_pairs']} pairs"
        out.append([
            r["processes"], chunks, r["pairs"], fmt(r["seconds"], 1), fmt(rate, 2),
            fmt(speedup, 2), f"{100 * speedup / r['processes']:.0f} %",
            fmt(r["cpu_seconds"] / r["pairs"], 3), r["load_start"],
        ])  # fmt: skip
    header = ["processes", "chunks", "pairs", "wall (s)", "pairs/s", "speed-up",
              "efficiency", "CPU s / pair", "load at start (1/5/15 min)"]  # fmt: skip
    return markdown_table(header, out)


def main(argv: list[str] | None = None) -> Path:
    args = parse_args(argv)
    import cv2
    import torch

    from mfg_lightning.core.machine import cpu_kind, usable_cores

    # The 1-process row runs in this process: one thread, as each worker of the other rows.
    torch.set_num_threads(args.threads or 1)
    cv2.setNumThreads(args.threads or 1)
    args.work.mkdir(parents=True, exist_ok=True)
    # made first, so that its environment's wall time covers the measurements (a resumed run:
    # the stages it measured)
    report = Report("scaleout", "Scale-out: data-parallel training (DDP)", args.out)
    rows = [measure(args, n) for n in args.processes]
    if max(args.processes) > 2 * args.sequences:
        rows.append(measure(args, max(args.processes), whole=True))
    kind, cores = cpu_kind(), usable_cores()
    report.add(
        f"CPU **{kind}**, {cores} usable cores. `SyntheticDataModule.prepare_data()` with "
        f"`flow=dis` (DIS `{args.preset}`, rendered at {args.height} × {args.width}) on "
        f"{args.sequences} procedural training and {args.sequences} test trajectories of "
        f"{args.frames} frames, into an empty cache, once per row; `dataset.prepare_workers` "
        "processes (1: in this process, on one thread), each worker on one thread, sharing "
        "chunks of consecutive frames from every sequence of both splits."
        + (" Tiny setting: the numbers mean nothing." if args.tiny else "")
    )
    report.add(table(rows))
    report.add(
        "pairs/s = pairs / wall time of the whole call: the workers' start (each imports torch "
        "and OpenCV), rendering, DIS, the cache writes, the flow quality and the pictures. "
        "Speed-up = pairs/s over the 1-process row's; efficiency = speed-up / processes (100 %: "
        "every process as fast as one alone). CPU s / pair: this process and its workers "
        "together; where it rises with the processes they contend for memory bandwidth, shared "
        "caches or clock speed, and efficiency lost beyond that rise is idle cores (start-up, "
        "the last chunks). A 'whole sequences' row shares the same work out one sequence per "
        "process, as preparation did before chunks: no more processes than sequences. Rows run "
        "one after the other on the same machine; each records its load average, since the "
        "machine may be shared."
    )
    return report.write_section(MARKER, HEADING)


if __name__ == "__main__":
    main()
