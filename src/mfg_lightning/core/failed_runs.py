"""What a run that fails leaves behind: nothing, when it failed on the user's input before it
produced anything; otherwise a ``FAILED`` marker (the error, one line) beside its files, without
the TensorBoard event files that hold no event, and the error in its log.

:mod:`mfg_lightning.core.errors` calls :func:`settle_failed_run` for every entry point; the
notebooks and run helpers skip a directory with a ``FAILED`` marker (:func:`is_failed`,
:func:`newest_run`). Standard library only.
"""

from __future__ import annotations

import logging
import os
import struct
from collections.abc import Iterable
from pathlib import Path

__all__ = [
    "FAILED",
    "event_count",
    "is_failed",
    "newest_run",
    "remove_empty_event_files",
    "settle_failed_run",
]

#: The marker file of a failed run directory; it holds the error, one line.
FAILED = "FAILED"
#: What Hydra and a run write before any work is done: removed when the run fails on its input.
_PRELUDE = {".hydra/config.yaml", ".hydra/hydra.yaml", ".hydra/overrides.yaml", "config.yaml",
            "run_info.json"}  # fmt: skip


def event_count(path: Path) -> int:
    """The number of records in a TensorBoard event file (TFRecord framing: a little-endian
    uint64 length, its CRC, the data, the data's CRC). The first record is the file's version,
    so a file with one record holds no event. A file cut short counts its whole records."""
    count, data = 0, path.read_bytes()
    at = 0
    while at + 12 <= len(data):
        (length,) = struct.unpack_from("<Q", data, at)
        at += 12 + length + 4
        if at > len(data):
            break
        count += 1
    return count


def remove_empty_event_files(run_dir: Path) -> list[Path]:
    """Remove the event files under ``run_dir`` that hold no event, then the folders that held
    nothing else; returns the files removed."""
    removed = []
    for path in sorted(run_dir.rglob("events.out.tfevents.*")):
        if path.is_file() and event_count(path) <= 1:
            path.unlink()
            removed.append(path)
    for folder in sorted({p.parent for p in removed}, key=lambda p: len(p.parts), reverse=True):
        while folder != run_dir and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
            folder = folder.parent
    return removed


def _prelude_only(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds only what is written before any work (its ``*.log`` files too)."""
    for path in run_dir.rglob("*"):
        rel = path.relative_to(run_dir).as_posix()
        log = path.suffix == ".log" and "/" not in rel
        if path.is_file() and rel not in _PRELUDE and not log:
            return False
    return True


def _log_to_files(message: str, exc: BaseException | None) -> None:
    """Write ``message`` (and the traceback of ``exc``) to the log files of the root logger only:
    the terminal has the error already, once."""
    info = None if exc is None else (type(exc), exc, exc.__traceback__)
    record = logging.LogRecord("mfg_lightning", logging.ERROR, __file__, 0, message, None, info)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)


def settle_failed_run(
    run_dir: Path | None, message: str, err: BaseException, user: bool, keep: bool = False
) -> None:
    """Leave a failed run's directory as the module docstring says.

    Args:
        run_dir: the run (or multirun job) directory; None: nothing to do.
        message: the error, one line (``error: …`` for a user error).
        err: the exception (its traceback goes to the log for a bug).
        user: the error is the user's input (exit status 2), not a bug.
        keep: never remove the directory (a multirun job: ``mfg_lightning.report`` reads the
            reason from its log).
    """
    _log_to_files(message, None if user else err)
    if run_dir is None or not run_dir.is_dir():
        return
    remove_empty_event_files(run_dir)
    cwd = Path.cwd().resolve()
    holds_cwd = run_dir.resolve() in (cwd, *cwd.parents)
    if user and not keep and not holds_cwd and _prelude_only(run_dir):
        root = logging.getLogger()
        for handler in list(root.handlers):  # release the log file before removing it
            if (
                isinstance(handler, logging.FileHandler)
                and run_dir.resolve() in Path(handler.baseFilename).resolve().parents
            ):
                root.removeHandler(handler)
                handler.close()
        for path in sorted(run_dir.rglob("*"), key=lambda p: len(p.parts), reverse=True):
            path.unlink() if path.is_file() else path.rmdir()
        run_dir.rmdir()
        # The two folders Hydra made above it (<log_dir>/train/runs) go too while empty; the
        # log directory itself, and anything holding the working directory, stay.
        parent = run_dir.resolve().parent
        for _ in range(2):
            if parent in (cwd, *cwd.parents) or any(parent.iterdir()):
                break
            parent.rmdir()
            parent = parent.parent
        return
    (run_dir / FAILED).write_text(message.strip().replace("\n", " ") + "\n")


def is_failed(run_dir: str | os.PathLike[str]) -> bool:
    """Whether a run directory is marked failed."""
    return (Path(run_dir) / FAILED).is_file()


def newest_run(run_dirs: Iterable[Path]) -> Path | None:
    """The most recently modified of ``run_dirs`` that is not marked failed, or None."""
    alive = [Path(d) for d in run_dirs if not is_failed(d)]
    return max(alive, key=lambda p: p.stat().st_mtime, default=None)
