"""What every benchmark script shares: the environment record, Markdown tables, results files.

Tables and numbers are :mod:`mfg_lightning.core.tables`' (``markdown_table`` and ``fmt`` here).

A results file is Markdown: a title, the exact command that produced it, the machine (cores, CPU
with its AVX2 / AVX-512 / AVX512-BF16 / AMX features, load average at the start and the end,
since the machine may be shared) and the library versions, then the script's tables and notes.
Scripts print the same text they write.
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


#: A ratio's repeats whose range leaves ± this fraction of their median are marked noisy.
NOISY = 0.05


def ratio_cell(ratios: list[float], digits: int = 3) -> str:
    """``median (min–max)`` of a ratio's repeats, followed by ``noisy`` when the range leaves
    ±:data:`NOISY` of the median (more repeats, or a quieter machine, would be needed to
    trust the median to that)."""
    import statistics

    mid = statistics.median(ratios)
    cell = f"{mid:.{digits}f} ({min(ratios):.{digits}f}–{max(ratios):.{digits}f})"
    if min(ratios) < (1 - NOISY) * mid or max(ratios) > (1 + NOISY) * mid:
        cell += " noisy"
    return cell


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


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and of its children that have ended (a
    process pool's workers once it is shut down)."""
    import resource

    own, children = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def cpu_model() -> str:
    """The CPU's model name (Linux), else what :mod:`platform` knows."""
    from mfg_lightning.core.machine import cpu_model as model

    return model()


def cpu_description() -> str:
    """The CPU's model and whether it has AVX2, AVX-512, AVX512-BF16 and AMX, plus the CPU
    kernels torch dispatches to, e.g. ``"AMD EPYC (AVX2 yes, AVX-512 no, AVX512-BF16 no, AMX
    no; torch: AVX2)"``: what every CPU time of a benchmark depends on."""
    import torch

    from mfg_lightning.core.machine import cpu_vector_features

    features = [f"{k} {'yes' if v else 'no'}" for k, v in cpu_vector_features().items()]
    capability = getattr(torch.backends.cpu, "get_cpu_capability", lambda: "unknown")()
    return f"{cpu_model()} ({', '.join(features)}; torch: {capability})"


def versions() -> dict[str, str]:
    """Versions of the libraries a number depends on (``-`` for one that is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version()}
    for dist in ("torch", "lightning", "torchmetrics", "numpy"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "-"
    # OpenCV under whichever wheel provides cv2 (the project's: the contrib build)
    for dist in ("opencv-contrib-python-headless", "opencv-python-headless"):
        try:
            out[dist] = version(dist)
            break
        except PackageNotFoundError:
            continue
    else:
        out["opencv"] = "-"
    try:
        from mfg_lightning.run.runs import git_commit, git_dirty

        commit = (git_commit() or "-")[:12]
        out["mfg-lightning commit"] = commit + ("+dirty" if commit != "-" and git_dirty() else "")
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
        from mfg_lightning.core.machine import usable_cores

        usable = usable_cores()
        rows = [
            ("command", f"`{command_line()}`"),
            ("date (UTC)", time.strftime("%Y-%m-%d %H:%M", time.gmtime(self.started))),
            ("wall time", f"{time.time() - self.started:.0f} s"),
            ("CPU", cpu_description()),
            ("cores (usable / total)", f"{usable} / {os.cpu_count()}"),
            ("torch threads", str(self.threads)),
            ("load average at start (1/5/15 min)", self.load_start),
            ("load average at end (1/5/15 min)", load_average()),
            *((k, v) for k, v in versions().items()),
        ]
        return markdown_table(["", ""], rows)

    def write(self) -> Path:
        """Write ``<out_dir>/<name>.md`` (atomically) and return its path. The marked sections
        another script wrote into the old file (:meth:`write_section`) are kept, before the
        environment."""
        from mfg_lightning.core.atomic import atomic_write_text

        path = self.out_dir / f"{self.name}.md"
        kept = marked_blocks(path.read_text()) if path.is_file() else []
        text = f"# {self.title}\n\n" + "\n".join(self.sections)
        text += "".join(f"\n{block}" for block in kept)
        text += "\n## Environment\n\n" + self.environment()
        path = atomic_write_text(path, text)
        print(f"wrote {path}", flush=True)
        return path

    def write_section(self, marker: str, heading: str) -> Path:
        """Write this report's sections as one section of ``<out_dir>/<name>.md``, leaving the
        rest of the file as it is: ``## heading``, the sections, then their own environment,
        between ``<!-- marker:start -->`` and ``<!-- marker:end -->``, replacing the old block
        of that marker (a new one goes before the file's ``## Environment``; a new file gets
        the title). Returns the path."""
        from mfg_lightning.core.atomic import atomic_write_text

        body = f"## {heading}\n\n" + "\n".join(self.sections)
        body += f"\n### Environment of this section\n\n{self.environment()}"
        path = self.out_dir / f"{self.name}.md"
        old = path.read_text() if path.is_file() else f"# {self.title}\n"
        path = atomic_write_text(path, replace_marked(old, marker, body, before="## Environment"))
        print(f"wrote {path}", flush=True)
        return path


def _markers(marker: str) -> tuple[str, str]:
    return f"<!-- {marker}:start -->", f"<!-- {marker}:end -->"


def marked_blocks(text: str) -> list[str]:
    """Every ``<!-- name:start -->`` … ``<!-- name:end -->`` block of ``text``, markers
    included, each ending with a newline, in order."""
    import re

    found = re.finditer(r"<!-- ([\w-]+):start -->\n.*?<!-- \1:end -->\n?", text, flags=re.S)
    return [m.group(0).rstrip("\n") + "\n" for m in found]


def write_marked(path: Path, marker: str, body: str) -> None:
    """Replace the block between ``marker``'s lines in the file ``path`` (a README) with
    ``body``; a file without the marker is left alone, with a warning."""
    from mfg_lightning.core.atomic import atomic_write_text

    text = path.read_text()
    if _markers(marker)[0] not in text:
        print(f"warning: {path} has no <!-- {marker}:start --> marker: not updated", flush=True)
        return
    atomic_write_text(path, replace_marked(text, marker, body))
    print(f"wrote {path}", flush=True)


def replace_marked(text: str, marker: str, body: str, before: str | None = None) -> str:
    """``text`` with the block of ``marker`` (:func:`marked_blocks`) holding ``body``: in place
    of the old block, or else inserted before the first line that starts with ``before``, or
    else appended."""
    start, end = _markers(marker)
    block = f"{start}\n{body.rstrip()}\n{end}\n"
    if start in text and end in text.split(start, 1)[1]:
        head, rest = text.split(start, 1)
        tail = rest.split(end, 1)[1].lstrip("\n")
        return head + block + ("\n" + tail if tail else "")
    lines = text.splitlines(keepends=True)
    at = next(
        (i for i, ln in enumerate(lines) if before is not None and ln.startswith(before)), None
    )
    if at is None:
        return text.rstrip("\n") + "\n\n" + block
    return "".join(lines[:at]) + block + "\n" + "".join(lines[at:])
