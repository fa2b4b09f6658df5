"""Atomic file writes: a reader (or a run killed mid-write) never sees a half-written file.

Kept free of heavy imports (torch, lightning) so that light command-line tools can use it.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, durable: bool = True) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same directory, then rename.

    The temporary file is fsynced before ``os.replace`` (atomic on POSIX and Windows), so the
    destination holds either its old content or the new one. ``durable=False`` skips the fsync:
    a reader or a killed process still never sees half a file, but after a power loss the
    destination may be empty or torn; only for files that are verified on read and can be
    computed again (the sample cache's entries, each with a CRC). New files get the permissions a
    plain ``open()`` would give (the umask decides); an existing file keeps its mode. A failure
    (full disk, say) removes the temporary file and leaves the destination untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            if durable:
                fh.flush()
                os.fsync(fh.fileno())
        if path.exists():
            os.chmod(tmp, path.stat().st_mode & 0o7777)
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        if err.errno is None or err.filename is not None:
            raise
        # A failed write() names no file: name the destination (e.g. "No space left on device").
        raise OSError(err.errno, err.strerror, str(path)) from err
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """:func:`atomic_write_bytes` for UTF-8 text with ``\\n`` line endings."""
    return atomic_write_bytes(path, text.encode("utf-8"))
