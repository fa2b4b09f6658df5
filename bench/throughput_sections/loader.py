"""3. Does the data keep up: loader-only samples per second (the exact-flow generator in the
training process and in one DataLoader worker; cached rendered DIS flow) and training on the
real loader at each precision against the same model on batches held in memory; then where an
exact-flow sample's time goes."""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import fmt, markdown_table

from .measure import PRECISIONS, Run, datamodule, make_batches, median_of
from .training import lightning_rate


def generator_rate(overrides: list[str], n: int, repeats: int) -> float:
    """Samples per second of the synthetic dataset's ``__getitem__`` (one process)."""
    dataset = datamodule(overrides).dataset("train")

    def rate() -> float:
        start = time.perf_counter()
        for i in range(n):
            dataset[i]
        return n / (time.perf_counter() - start)

    return median_of({"generator": rate}, repeats)["generator"]


def generator_profile(overrides: list[str], n: int) -> list[tuple[str, float]]:
    """Where a synthetic sample's time goes: the package's functions (and the random draws),
    cumulative milliseconds per sample under ``cProfile``, most expensive first."""
    import cProfile
    import pstats

    dataset = datamodule(overrides).dataset("train")
    dataset[0]
    profiler = cProfile.Profile()
    profiler.enable()
    for i in range(n):
        dataset[i]
    profiler.disable()
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    rows = []
    for (path, _, func), (_, _, _, cumulative, _) in stats.items():
        if "mfg_lightning" in path:
            name = f"{Path(path).stem}.{func}"
        elif path == "~" and "numpy.random" in func:
            name = func.strip("<>").replace("method ", "")
        else:
            continue
        rows.append((name, 1e3 * cumulative / n))
    return sorted(rows, key=lambda r: -r[1])[:10]


def loader_rate(loader: Any, batches: int) -> float:
    """Samples per second of iterating ``loader`` (after its first batch: worker start-up)."""
    it = iter(loader)
    next(it)
    start, n = time.perf_counter(), 0
    for _ in range(batches):
        n += next(it)["flow"].shape[0]
    return n / (time.perf_counter() - start)


def dis_row(run: Run, batch: int) -> tuple[list[str], float]:
    """The loader-only row of cached rendered DIS flow (a small ``flow=dis`` cache, filled by
    ``prepare_data`` first) and the seconds that filling took."""
    with tempfile.TemporaryDirectory() as cache:
        frames = 21 if run.args.tiny else 60
        dis = datamodule(
            [*run.base, "flow=dis", f"dataset.cache_dir={cache}",
             f"dataset.sequence_length={frames}", "dataset.train_sequences=1",
             "dataset.test_sequences=1", f"dataset.batch_size={batch}"]
        )  # fmt: skip
        start = time.perf_counter()
        dis.prepare_data()
        prepare_s = time.perf_counter() - start
        n_dis = len(dis.dataset("train"))
        dis_batches = max(1, n_dis // batch - 1)
        rate = statistics.median(
            loader_rate(dis.train_dataloader(), dis_batches)
            for _ in range(run.args.candidate_repeats)
        )
    label = (
        f"cached rendered DIS flow (`flow=dis`, {n_dis} cached train pairs), train loader, the "
        "training process"
    )
    return [label, fmt(rate, 0)], prepare_s


def on_loaders_row(run: Run, name: str, loaders: dict[int, Any], batch: int) -> list[str]:
    """Training at ``name``'s precision on batches in memory and on each loader (by its
    ``num_workers``): the rates and the share of the time spent waiting on data."""
    args, precision = run.args, PRECISIONS[name]
    batches = make_batches(run.samples, batch)
    steps = 4 if args.tiny else 30
    mem = statistics.median(
        lightning_rate(run.base, batches, args.warmup, steps, precision)
        for _ in range(args.candidate_repeats)
    )
    row = [name, fmt(mem, 1)]
    for dm in loaders.values():
        real = statistics.median(
            lightning_rate(run.base, None, args.warmup, steps, precision,
                           loader=dm.train_dataloader(), batch_size=batch)
            for _ in range(args.candidate_repeats)
        )  # fmt: skip
        row += [fmt(real, 1), f"{100 * (1 - real / mem):.0f} %"]
    return row


def section(run: Run) -> None:
    """Measure the loaders alone and training on them; add both tables and the profile."""
    args = run.args
    batch = run.cfg.dataset.batch_size if not args.tiny else 4
    n_batches = 2 if args.tiny else 20
    gen = generator_rate(run.base, 20 if args.tiny else 300, args.candidate_repeats)
    load_rows = [["exact-flow generator, `__getitem__` in the training process", fmt(gen, 0)]]
    loaders = {}
    for workers in (0, 1):
        dm = datamodule(
            [*run.base, f"dataset.num_workers={workers}", f"dataset.batch_size={batch}"]
        )
        loaders[workers] = dm
        rate = statistics.median(
            loader_rate(dm.train_dataloader(), n_batches) for _ in range(args.candidate_repeats)
        )
        where = "the training process" if workers == 0 else "one DataLoader worker"
        load_rows.append([f"exact-flow generator, train loader, {where}", fmt(rate, 0)])
    dis, prepare_s = dis_row(run, batch)
    load_rows.append(dis)
    train_rows = [on_loaders_row(run, name, loaders, batch) for name in PRECISIONS]
    run.report.add(
        f"## The data: loader-only rates and training on the real loader (batch {batch})\n\n"
        + markdown_table(["loader only", "samples/s"], load_rows)
        + f"\nLoader-only: iterating the configured train DataLoader (shuffled, collated, batch "
        f"{batch}) {n_batches} batches after its first one (a worker's start-up excluded); "
        f"the DIS cache was filled first by `prepare_data` ({prepare_s:.0f} s: render and "
        "estimate every pair), then read.\n\nTraining on the real loader:\n\n"
        + markdown_table(
            [
                "precision",
                "training, batches in memory (samples/s)",
                "training, generator in process (`num_workers=0`, the default)",
                "time waiting on data",
                "training, 1 loader worker",
                "time waiting on data",
            ],
            train_rows,
        )
        + '\nLightning, the same model and precision; "waiting on data" = 1 − rate on the real '
        "loader / rate on batches in memory. With `num_workers=0` the generator runs between the "
        "steps, so its time adds to every step; a worker overlaps it, but takes one of the "
        "machine's cores from the training's threads."
    )
    profile = generator_profile(run.base, 10 if args.tiny else 200)
    run.report.add(
        "Where an exact-flow sample's time goes (cProfile, cumulative, so nested calls "
        "repeat):\n\n"
        + markdown_table(
            ["function", "ms / sample"], [[f"`{name}`", fmt(ms, 3)] for name, ms in profile]
        )
    )
