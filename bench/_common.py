"""What every benchmark script shares: the environment record, Markdown tables, results files.

Tables and numbers are :mod:`mfg_lightning.core.tables`' (``markdown_table`` and ``fmt`` here).

A results file is Markdown: a title, the exact command that produced it, the machine (cores, CPU,
load average at the start and the end, since the machine may be shared) and the library versions,
then the script's tables and notes. Scripts print the same text they write.
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

# One number format for every table of the project: bench scripts import it from here.
from mfg_lightning.core.tables import Column, Table, fmt  # noqa: F401

REPO = Path(__file__).resolve().parents[1]
RESULTS_DIR = REPO / "bench" / "results"
#: KITTI odometry ground-truth poses, beside the repository (``../shared``).
DEFAULT_POSES_DIR = REPO.parent / "shared" / "data" / "kitti_odometry" / "poses"
#: ``--tiny``: the model and input size of ``conf/debug/tiny.yaml``, for seconds-long smoke runs.
TINY_OVERRIDES = (
    "dataset.height=32",
    "dataset.width=64",
    "model.net.hidden_units=64",
    "model.net.channels=[8,8,16,16,32]",
)


def add_common_arguments(
    parser: argparse.ArgumentParser,
    threads: str = "torch threads (default: all)",
    tiny: str = "seconds-long smoke run (tiny model)",
) -> argparse.ArgumentParser:
    """The options every benchmark script takes: ``--threads``, ``--out`` (results directory,
    default ``bench/results``) and ``--tiny``; ``threads`` and ``tiny`` are their help texts."""
    parser.add_argument("--threads", type=int, default=None, help=threads)
    parser.add_argument("--out", type=Path, default=None, help="results directory")
    parser.add_argument("--tiny", action="store_true", help=tiny)
    return parser


def load_average() -> str:
    """The 1, 5 and 15 minute load averages, e.g. ``"0.52 0.61 0.70"`` (n/a where unknown)."""
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def cpu_model() -> str:
    """The CPU's model name (Linux), else what :mod:`platform` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def versions() -> dict[str, str]:
    """Versions of the libraries a number depends on (``-`` for one that is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version()}
    for dist in ("torch", "lightning", "torchmetrics", "numpy", "opencv-python-headless"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "-"
    try:
        from mfg_lightning.run.runs import git_commit

        out["mfg-lightning commit"] = (git_commit() or "-")[:12]
    except ImportError:
        out["mfg-lightning commit"] = "-"
    return out


def command_line() -> str:
    """The command that is running, as a user would type it from the repository root (paths
    made portable: :func:`mfg_lightning.core.paths.portable_path`)."""
    from mfg_lightning.core.paths import portable_path
    from mfg_lightning.flow.cache import default_cache_dir

    cache = default_cache_dir()
    return shlex.join(["python", *(portable_path(a, REPO, cache) for a in sys.argv)])


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub Markdown table (:class:`mfg_lightning.core.tables.Table`; cells converted with
    ``str``,
    so the scripts format their numbers with :func:`fmt`)."""
    table = Table([Column(str(h)) for h in header], [[str(c) for c in row] for row in rows])
    return table.markdown()


class Report:
    """Collects a benchmark's sections and writes them with the environment.

    Args:
        name: file stem under the results directory (``accuracy`` → ``accuracy.md``).
        title: the Markdown title.
        out_dir: where to write (default ``bench/results``).
    """

    def __init__(self, name: str, title: str, out_dir: Path | None = None) -> None:
        import torch

        self.name, self.title = name, title
        self.out_dir = Path(out_dir) if out_dir is not None else RESULTS_DIR
        self.sections: list[str] = []
        self.started = time.time()
        self.load_start = load_average()
        self.threads = torch.get_num_threads()

    def add(self, text: str) -> None:
        """Append a Markdown section (a table, a heading, a paragraph)."""
        self.sections.append(text.rstrip() + "\n")
        print(text.rstrip() + "\n", flush=True)

    def environment(self) -> str:
        """The environment block: command, cores, CPU, threads, load averages and versions."""
        try:
            usable = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            usable = os.cpu_count() or 0
        rows = [
            ("command", f"`{command_line()}`"),
            ("date (UTC)", time.strftime("%Y-%m-%d %H:%M", time.gmtime(self.started))),
            ("wall time", f"{time.time() - self.started:.0f} s"),
            ("CPU", cpu_model()),
            ("cores (usable / total)", f"{usable} / {os.cpu_count()}"),
            ("torch threads", str(self.threads)),
            ("load average at start (1/5/15 min)", self.load_start),
            ("load average at end (1/5/15 min)", load_average()),
            *((k, v) for k, v in versions().items()),
        ]
        return markdown_table(["", ""], rows)

    def write(self) -> Path:
        """Write ``<out_dir>/<name>.md`` (atomically) and return its path."""
        from mfg_lightning.core.atomic import atomic_write_text

        text = f"# {self.title}\n\n" + "\n".join(self.sections)
        text += "\n## Environment\n\n" + self.environment()
        path = atomic_write_text(self.out_dir / f"{self.name}.md", text)
        print(f"wrote {path}", flush=True)
        return path
