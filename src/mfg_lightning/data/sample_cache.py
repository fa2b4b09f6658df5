"""Samples computed once: a memory tier up to a stated size and a disk tier beyond it, which a
background thread (:class:`~mfg_lightning.data.prefetch.Prefetcher`) may fill ahead of the
training loader.

A ``flow=exact`` sample is a pure function of ``(scene seed, sequence, source, target)`` and its
dataset's settings, so every epoch would regenerate the same samples: a :class:`SampleStore`
keeps each one the first time it is computed: in memory as its dataset hands it out, on disk
encoded as a few numpy arrays (:data:`Arrays`, :class:`Codec`).

* **Memory**: up to :class:`MemoryBudget` bytes per process, which the splits of a DataModule
  share (first come, first kept: nothing is evicted). A DataLoader worker process gets
  ``1 / num_workers`` of the budget, so that the workers of one loader together stay within it.
* **Disk**: ``<cache_dir>/<namespace>/<key>/<entry>``, ``<key>`` a hash of everything that
  changes a sample (:class:`~mfg_lightning.flow.estimators.FlowCache` makes the folder and its
  ``meta.json``), shared by later epochs beyond the memory and by later runs with the same
  settings. An entry is one file (:func:`encode_entry`: the arrays and a CRC-32), written
  atomically (:mod:`mfg_lightning.core.atomic`); on read its CRC, names, dtypes and shapes are
  verified, and an entry that fails is warned about (naming the file) and computed again.
* **Once**: two threads asking for the same sample (the loader and the
  :class:`~mfg_lightning.data.prefetch.Prefetcher`) share one computation.

:func:`source_digest` hashes the source files a sample is computed by, for the keys of this cache
and of the rendered worlds' flow cache.
"""

from __future__ import annotations

import ast
import hashlib
import importlib
import importlib.util
import json
import logging
import math
import os
import struct
import threading
import zlib
from collections.abc import Callable, Hashable, Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Generic, TypeVar

import numpy as np

from mfg_lightning.core.atomic import atomic_write_bytes

log = logging.getLogger(__name__)

#: A cached sample: field name → C-contiguous array.
Arrays = dict[str, np.ndarray]
#: The fields an entry must have: name → (dtype, shape), ``None`` for a dimension of any length.
FieldSpec = Mapping[str, tuple[np.dtype, tuple[int | None, ...]]]
#: A sample in the form a :class:`SampleStore` keeps it in memory (:class:`Codec`).
V = TypeVar("V")


@dataclass(frozen=True)
class SampleCacheSettings:
    """``dataset.sample_cache``.

    Attributes:
        memory_mb: what one process keeps in memory, MB (2**20 bytes), its splits together; 0: no
            memory tier.
        disk: keep samples on disk as well, under the dataset's ``cache_dir`` (none: no disk
            tier).
    """

    memory_mb: float = 1024.0
    disk: bool = True

    @classmethod
    def parse(cls, cfg: Mapping[str, Any] | SampleCacheSettings | None) -> SampleCacheSettings:
        """The settings of a ``dataset.sample_cache`` config (None: the defaults); a bad one is a
        ``ValueError`` naming its key."""
        if isinstance(cfg, SampleCacheSettings):
            return cfg
        fields = dict(cfg or {})
        unknown = sorted(set(fields) - {"memory_mb", "disk"})
        if unknown:
            raise ValueError(
                f"unknown dataset.sample_cache setting(s) {unknown}; known: disk, memory_mb"
            )
        memory = fields.get("memory_mb", cls.memory_mb)
        if isinstance(memory, bool) or not isinstance(memory, int | float) or not memory >= 0:
            raise ValueError(f"dataset.sample_cache.memory_mb must be ≥ 0 MB, got {memory!r}")
        disk = fields.get("disk", cls.disk)
        if not isinstance(disk, bool):
            raise ValueError(f"dataset.sample_cache.disk must be true or false, got {disk!r}")
        return cls(float(memory), disk)


class _PerProcess:
    """State that belongs to one process: a forked child (a DataLoader worker) or an unpickled
    copy starts it afresh (:meth:`_reset`), because the parent's lock may be held by a thread
    that does not exist in the child and its in-flight computations will never finish there."""

    #: The attributes :meth:`_reset` makes, left out of a pickled copy.
    _process_local: tuple[str, ...] = ("_pid", "_lock")

    def __init__(self) -> None:
        self._reset()

    def _reset(self) -> None:
        self._pid = os.getpid()
        self._lock = threading.Lock()

    def _here(self) -> None:
        if self._pid != os.getpid():
            self._reset()

    def __getstate__(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k not in self._process_local}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._reset()


class MemoryBudget(_PerProcess):
    """Bytes that the memory tiers of one process may hold together (nothing is evicted: a
    tier keeps a sample when the budget has room for it, else leaves it to the disk).

    In a DataLoader worker the budget is ``megabytes / num_workers`` and counts only what that
    worker keeps (what it inherited from the parent by ``fork`` is shared, not copied).

    Args:
        megabytes: the budget, MB (2**20 bytes).
    """

    def __init__(self, megabytes: float) -> None:
        self.limit = int(float(megabytes) * 2**20)
        super().__init__()

    def _reset(self) -> None:
        super()._reset()
        self.used = 0
        self._share: int | None = None

    @property
    def share(self) -> int:
        """This process's bytes: the budget, or its ``1 / num_workers`` in a loader worker.
        Decided on first use (a worker unpickles its dataset before it knows it is one)."""
        self._here()
        if self._share is None:
            from torch.utils.data import get_worker_info

            info = get_worker_info()
            self._share = self.limit // info.num_workers if info is not None else self.limit
        return self._share

    def reserve(self, nbytes: int) -> bool:
        """Count ``nbytes`` against the budget if they fit; whether they did."""
        share = self.share
        with self._lock:
            if self.used + nbytes > share:
                return False
            self.used += nbytes
            return True


# -- entries on disk ------------------------------------------------------------------------
#
# One file per sample, read whole with one system call and decoded without parsing a zip or
# .npy headers (an .npz of the same arrays took 1.4 ms to load, generating the sample 5.5 ms):
#
#   MAGIC (8 bytes) | header length n (uint32, little-endian) | CRC-32 of the rest (uint32) |
#   header (n bytes of JSON: [[name, dtype, shape], ...]) | the arrays' bytes, C order, in order
#
# The CRC covers the header and the arrays: a flipped byte after the first 16 fails it, one in
# them the magic, the CRC or the header's lengths; a truncated file fails the lengths.

MAGIC = b"MFGSMPL1"
_PREFIX = struct.Struct("<8sII")


def encode_entry(arrays: Mapping[str, np.ndarray]) -> bytes:
    """The bytes of an entry holding ``arrays`` (see the layout above)."""
    parts = [np.ascontiguousarray(a) for a in arrays.values()]
    header = json.dumps(
        [[name, a.dtype.str, list(a.shape)] for name, a in zip(arrays, parts, strict=True)]
    ).encode()
    body = b"".join([header, *(a.tobytes() for a in parts)])
    return _PREFIX.pack(MAGIC, len(header), zlib.crc32(body)) + body


def decode_entry(data: bytes, fields: FieldSpec) -> tuple[Arrays | None, str]:
    """``(arrays, "")`` from an entry's bytes, or ``(None, what is wrong)``: a bad magic, length
    or CRC, other arrays than ``fields`` or another dtype or shape. The arrays are read-only
    views of ``data``."""
    if len(data) < _PREFIX.size:
        return None, f"{len(data)} bytes: truncated"
    magic, n, crc = _PREFIX.unpack_from(data)
    if magic != MAGIC:
        return None, "not a sample cache entry (bad magic)"
    body = memoryview(data)[_PREFIX.size :]
    if n > len(body) or zlib.crc32(body) != crc:
        return None, f"CRC mismatch ({len(data)} bytes): truncated or corrupt"
    try:
        header = [(str(name), np.dtype(dtype), tuple(map(int, shape)))
                  for name, dtype, shape in json.loads(bytes(body[:n]))]  # fmt: skip
    except (ValueError, TypeError) as err:  # (a CRC that matches: written so, by another writer)
        return None, f"bad header ({err})"
    names = [name for name, _, _ in header]
    if names != list(fields):
        return None, f"arrays {names}, expected {list(fields)}"
    arrays, offset = {}, n
    for (name, dtype, shape), (want_dtype, want_shape) in zip(header, fields.values(), strict=True):
        if (
            dtype != want_dtype
            or len(shape) != len(want_shape)
            or any(g < 0 or w not in (None, g) for g, w in zip(shape, want_shape, strict=True))
        ):
            return None, f"{name} is {dtype} {shape}, expected {want_dtype} {want_shape}"
        size = dtype.itemsize * math.prod(shape)
        if offset + size > len(body):
            return None, f"{name} runs past the end of the file"
        arrays[name] = np.frombuffer(body, dtype, math.prod(shape), offset).reshape(shape)
        offset += size
    if offset != len(body):
        return None, f"{len(body) - offset} bytes after the arrays"
    return arrays, ""


def read_entry(
    path: Path, fields: FieldSpec, validate: Callable[[Arrays], str | None] | None = None
) -> Arrays | None:
    """The arrays of the entry ``path``, verified (its CRC, then the arrays' names, dtypes and
    shapes against ``fields``, then ``validate``, which says what is wrong with a decodable
    entry, or None).

    Returns None when the file does not exist (silently) or cannot be used: unreadable,
    truncated, corrupt, other arrays, dtypes or shapes (a warning naming the file and the
    reason; the caller computes the sample again and overwrites the entry).
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as err:
        arrays, reason = None, f"unreadable: {err}"
    else:
        arrays, reason = decode_entry(data, fields)
        if arrays is not None and validate is not None:
            reason = validate(arrays) or ""
    if arrays is not None and not reason:
        return arrays
    log.warning("sample cache entry %s is unusable (%s): computing the sample again", path, reason)
    return None


def write_entry(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """Write ``arrays`` to ``path`` (:func:`encode_entry`) atomically: a reader, or a run
    killed mid-write, never sees half an entry."""
    # No fsync: it cost 0.35 ms an entry at 48 x 128, an eighth of generating the sample
    # (2.8 ms; 2 cores, avx512_bf16), and what a power loss can leave (an empty or torn file)
    # fails the CRC on read and is computed again.
    atomic_write_bytes(path, encode_entry(arrays), durable=False)


#: The future :meth:`SampleStore._claim` returns with a sample found in memory (never awaited).
_DONE: Future = Future()


class Codec(Generic[V]):
    """How a :class:`SampleStore` turns what it keeps in memory (a sample in the form its
    dataset hands out, ``V``) into the arrays of a disk entry and back.

    The default keeps the arrays themselves in memory. A dataset whose entries are compressed
    (bits for masks, the sparse object flow) gives its own: its memory tier then holds the
    decoded sample, so that a later epoch's read is a copy instead of a decoding.
    """

    def encode(self, value: V) -> Arrays:
        """The arrays of the disk entry of ``value`` (:func:`write_entry`)."""
        return value  # type: ignore[return-value]

    def decode(self, arrays: Arrays) -> V:
        """The sample of a disk entry's verified arrays (read-only views of the file's bytes)."""
        return arrays  # type: ignore[return-value]

    def nbytes(self, value: V) -> int:
        """The bytes ``value`` (a dict of arrays or tensors) holds, what the memory budget
        counts: a tensor's whole storage (a view keeps all of it)."""
        return sum(
            a.nbytes if isinstance(a, np.ndarray) else a.untyped_storage().nbytes()
            for a in value.values()  # type: ignore[attr-defined]
        )


class SampleStore(_PerProcess, Generic[V]):
    """The memory and disk tiers of one dataset, around the function that computes a sample.

    :meth:`fetch` returns a sample from memory, else read from disk, else computed (then kept in
    memory if the budget has room, and written to disk); :meth:`prefetch` does the same from a
    background thread without returning it. A sample being computed by one thread is waited for
    by the others, never computed twice. The sample returned is the stored one: callers copy
    before handing it out.

    Args:
        fields: what every disk entry holds (verified on every disk read).
        memory: the process's budget (None: no memory tier).
        root: the disk tier's directory (None: no disk tier).
        validate: a further check of an entry read from disk (what is wrong, or None).
        codec: the sample's form in memory and as a disk entry (None: the entry's arrays
            themselves, :class:`Codec`).
    """

    def __init__(
        self,
        fields: FieldSpec,
        memory: MemoryBudget | None = None,
        root: Path | None = None,
        validate: Callable[[Arrays], str | None] | None = None,
        codec: Codec[V] | None = None,
    ) -> None:
        self.fields = dict(fields)
        self.budget = memory
        self.root = root
        self.validate = validate
        self.codec: Codec[V] = codec or Codec()
        super().__init__()

    _process_local = (*_PerProcess._process_local, "_inflight")

    def _reset(self) -> None:
        super()._reset()
        # Memory entries of a parent are dropped in a pickled copy (__getstate__) but kept by a
        # fork, whose pages are shared; in-flight work is the parent's own.
        self.memory: dict[Hashable, V] = getattr(self, "memory", {})
        self._inflight: dict[Hashable, Future] = {}
        self.memory_full = self.budget is None
        #: How samples were served: from memory, read from disk, computed (by any thread), and
        #: how many of the computed or read ones the prefetch thread did.
        self.counts = {"memory": 0, "disk": 0, "computed": 0, "prefetched": 0}

    def __getstate__(self) -> dict[str, Any]:
        # A pickled dataset (a spawned worker) starts with an empty memory: shipping the
        # parent's samples would cost more than reading them back from disk.
        return {**super().__getstate__(), "memory": {}}

    def path(self, name: str) -> Path | None:
        """The disk entry ``<root>/<name>`` (None: no disk tier)."""
        return None if self.root is None else self.root / name

    def fetch(self, key: Hashable, name: str, compute: Callable[[], V]) -> V:
        """Sample ``key`` (disk entry ``name``), computing it at most once."""
        self._here()
        value, future, owned = self._claim(key)
        if value is not None:
            return value
        if not owned:  # another thread is on it
            return future.result()
        return self._produce(key, future, name, compute, prefetched=False)

    def prefetch(self, key: Hashable, name: str, compute: Callable[[], V]) -> bool:
        """Put sample ``key`` in memory (or on disk when memory is full) ahead of :meth:`fetch`.

        Returns False when nothing more can be kept (memory full and no disk tier): a
        prefetcher then stops instead of computing samples that would be thrown away.
        """
        self._here()
        path = self.path(name)
        if self.memory_full and (path is None or path.exists()):
            return path is not None
        _, future, owned = self._claim(key, count=False)
        if owned:
            self._produce(key, future, name, compute, prefetched=True)
        return True

    def _claim(self, key: Hashable, count: bool = True) -> tuple[V | None, Future, bool]:
        """``(sample, _, False)`` if ``key`` is in memory (counted as served from memory when
        ``count``); ``(None, future, False)`` if another thread is producing it; ``(None,
        future, True)`` if the caller now owns its production and must resolve ``future``."""
        with self._lock:
            value = self.memory.get(key)
            if value is not None:
                self.counts["memory"] += count
                return value, _DONE, False
            if key in self._inflight:
                return None, self._inflight[key], False
            future = self._inflight[key] = Future()
            return None, future, True

    def _produce(
        self,
        key: Hashable,
        future: Future,
        name: str,
        compute: Callable[[], V],
        prefetched: bool,
    ) -> V:
        """Read or compute the claimed ``key``, keep it, and hand it to any waiting thread."""
        try:
            path = self.path(name)
            arrays = None if path is None else read_entry(path, self.fields, self.validate)
            read = arrays is not None
            if arrays is not None:
                value = self.codec.decode(arrays)
            else:
                value = compute()
                if path is not None:
                    self._write(path, self.codec.encode(value))
            kept = self._keep(value)
        except BaseException as err:
            with self._lock:
                del self._inflight[key]
            future.set_exception(err)
            raise
        with self._lock:
            if kept:
                self.memory[key] = value
            del self._inflight[key]
            self.counts["disk" if read else "computed"] += 1
            self.counts["prefetched"] += prefetched
        future.set_result(value)
        return value

    def _keep(self, value: V) -> bool:
        """Whether the memory budget takes ``value`` (once it refuses one, the tier is full)."""
        if self.memory_full or self.budget is None:
            return False
        if self.budget.reserve(self.codec.nbytes(value)):
            return True
        self.memory_full = True
        return False

    def _write(self, path: Path, arrays: Arrays) -> None:
        """Write an entry; a failure (a full disk) turns the disk tier off with one warning
        instead of stopping the training for a cache."""
        try:
            write_entry(path, arrays)
        except OSError as err:
            log.warning("sample cache: cannot write %s (%s): not caching on disk", path, err)
            self.root = None


# --------------------------------------------------------------------------------------------
# Cache keys: the source a sample is computed by
# --------------------------------------------------------------------------------------------

_DIGESTS: dict[tuple[str, ...], str] = {}


def source_digest(*modules: ModuleType) -> str:
    """A digest of the source files of ``modules`` and of every :mod:`mfg_lightning.scene`
    module they import, directly or not (:func:`_scene_imports`): any change to the renderer or
    the scene generator, whichever of its stage modules it is in, changes it.

    Read once per process, so that one process keeps one cache key even if the files are
    edited while it runs (it runs the code it imported)."""
    key = tuple(m.__name__ for m in modules)
    if key not in _DIGESTS:
        h = hashlib.sha256()
        for module in _scene_imports(modules):
            h.update(Path(module.__file__).read_bytes())
        _DIGESTS[key] = h.hexdigest()[:16]
    return _DIGESTS[key]


def _scene_imports(modules: Sequence[ModuleType]) -> list[ModuleType]:
    """``modules`` and every ``mfg_lightning.scene`` module their source imports (at module
    level or in a function), directly or through one another, sorted by name (so the digest
    is a function of the sources alone, whatever else a process has imported)."""
    found: dict[str, ModuleType] = {}
    todo = list(modules)
    while todo:
        module = todo.pop()
        if module.__name__ in found:
            continue
        found[module.__name__] = module
        for node in ast.walk(ast.parse(Path(module.__file__).read_bytes())):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = "." * node.level + (node.module or "")
                base = importlib.util.resolve_name(base, module.__package__)
                # ``from package import module`` names modules too.
                names = [base, *(f"{base}.{alias.name}" for alias in node.names)]
            else:
                continue
            todo += [
                importlib.import_module(name)
                for name in names
                if name.startswith("mfg_lightning.scene.") and _is_module(name)
            ]
    return [found[name] for name in sorted(found)]


def _is_module(name: str) -> bool:
    """Whether ``name`` (dotted) is an importable module rather than a name inside one."""
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:  # a name inside a module: its parent is no package
        return False
