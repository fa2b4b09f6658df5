"""Property-based tests (hypothesis): every reader either refuses its input with the project's
one-line data error naming the file, or returns something that means what the format says.

What a result must mean, for every reader: a pose is a rigid transform (``RᵀR = I``,
``det R = +1``, bottom row ``0 0 0 1``, within the readers' stated
:data:`~mfg_lightning.core.data_errors.RIGID_TOLERANCE`); focal lengths are positive; frame
numbers are unique (as many poses come back as the file has rows); an image or flow field has the
size its header claims, within :data:`~mfg_lightning.flow.io.MAX_PIXELS`; a checkpoint that is
not loaded is called corrupt or unsafe, whichever it is, and nothing in it runs.

Two kinds of input: valid files garbled byte by byte or token by token, and files written from
header fields drawn by the strategies (widths, heights, shapes, dtypes, frame numbers, rotation
scales, focal lengths, quaternion norms, pickled globals). What Hypothesis found in the readers
before they checked these is kept in ``tests/data/fuzz_regressions/`` and read on every run.

Every corrupt batch pushed through a real ``Trainer.fit`` of the module is either refused with a
:class:`SampleError` naming its samples, or masked / skipped so that every weight stays finite.
"""

from __future__ import annotations

import functools
import io
import logging
import pickle
import re
import struct
import tempfile
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from conftest import quiet_trainer
from fake_datasets import npy_header_only, png_header_only
from mfg_lightning.core.data_errors import RIGID_TOLERANCE, DataFileError
from mfg_lightning.data.base import collate_samples
from mfg_lightning.data.kitti import read_kitti_calib
from mfg_lightning.data.kitti import read_kitti_poses_as_data_file as kitti_dataset_poses
from mfg_lightning.data.sample import SampleError
from mfg_lightning.data.synthetic import SyntheticDataModule
from mfg_lightning.data.vkitti_files import read_vkitti_extrinsics, read_vkitti_intrinsics
from mfg_lightning.flow import io as flow_io
from mfg_lightning.models.losses import MFGLoss
from mfg_lightning.models.mfg import MFG
from mfg_lightning.models.mfg_module import MFGLitModule
from mfg_lightning.run.agreed_steps import AgreedSteps, NonFiniteLossError
from mfg_lightning.run.checkpoints import CheckpointError, load_checkpoint
from mfg_lightning.trajectory import pose_io
from mfg_lightning.trajectory.pose_io import PoseFileError

FUZZ = settings(
    max_examples=40,
    deadline=None,
    derandomize=True,  # the same examples on every run: a deterministic suite
    database=None,  # and nothing remembered between runs: what matters is kept as files
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
HEADERS = settings(FUZZ, max_examples=30)
PROJECT_ERRORS = (DataFileError, PoseFileError)
REGRESSIONS = Path(__file__).parent / "data" / "fuzz_regressions"
MAX_PIXELS = 1 << 25  # the readers' stated bound (flow_io.MAX_PIXELS), restated: a property

# --------------------------------------------------------------------------------------------
# What a result means
# --------------------------------------------------------------------------------------------


def _finite(*arrays: np.ndarray) -> None:
    for a in arrays:
        assert np.isfinite(a).all(), "a reader returned non-finite numbers"


def _rigid(poses: np.ndarray) -> None:
    """``(N, 4, 4)`` rigid transforms within the stated tolerance."""
    assert poses.ndim == 3 and poses.shape[1:] == (4, 4) and len(poses) >= 1
    _finite(poses)
    R = poses[:, :3, :3]
    gram = np.einsum("nji,njk->nik", R, R)
    assert np.abs(gram - np.eye(3)).max() <= RIGID_TOLERANCE, "a pose is not a rotation"
    assert (np.linalg.det(R) > 1 - 2 * RIGID_TOLERANCE).all(), "a pose is a reflection"
    np.testing.assert_allclose(poses[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (len(poses), 1)))


def _size_within_bounds(height: int, width: int) -> None:
    assert height >= 1 and width >= 1, f"an empty {width}×{height} result"
    assert height * width <= MAX_PIXELS, f"{width}×{height} is beyond the stated bound"


def _flow(out: tuple[np.ndarray, np.ndarray]) -> tuple[int, int]:
    flow, valid = out
    assert flow.dtype == np.float32 and flow.ndim == 3 and flow.shape[2] == 2
    assert valid.dtype == bool and valid.shape == flow.shape[:2]
    _finite(flow)  # unknown or non-finite pixels are masked: flow 0, valid False
    _size_within_bounds(*flow.shape[:2])
    return flow.shape[0], flow.shape[1]


def _rgb(out: np.ndarray) -> tuple[int, int]:
    assert out.dtype == np.uint8 and out.ndim == 3 and out.shape[2] == 3
    _size_within_bounds(*out.shape[:2])
    return out.shape[0], out.shape[1]


def _depth(out: tuple[np.ndarray, np.ndarray]) -> tuple[int, int]:
    depth, far = out
    _finite(depth)
    assert depth.dtype == np.float32 and far.shape == depth.shape and (depth >= 0).all()
    _size_within_bounds(*depth.shape)
    return depth.shape[0], depth.shape[1]


def _image_size(out: tuple[int, int]) -> tuple[int, int]:
    assert all(isinstance(v, int) for v in out)
    _size_within_bounds(*out)
    return out


def _pose_rows(data: bytes) -> list[list[float]]:
    """The numbers of every pose line of a KITTI or TUM file, as the format defines them."""
    rows = []
    for chunk in data.split(b"\n"):
        fields = chunk.decode("utf-8").split()
        if fields and not fields[0].startswith("#"):
            rows.append([float(f) for f in fields])
    return rows


def _table_rows(data: bytes, camera: bool) -> list[list[float]]:
    """The rows after the header of a Virtual KITTI table (camera 0's, with ``camera``)."""
    rows = [line.split() for line in data.decode("utf-8").splitlines()[1:]]
    table = [[float(f) for f in row] for row in rows if row]
    return [row for row in table if not camera or row[1] == 0]


def _kitti_poses(poses: np.ndarray, data: bytes) -> None:
    _rigid(poses)
    assert len(poses) == len(_pose_rows(data)), "poses were merged or dropped"


def _pose_file(pose_file: pose_io.PoseFile, data: bytes) -> None:
    _kitti_poses(pose_file.poses, data)
    frames = pose_file.frame_indices()
    assert (np.diff(frames) > 0).all(), "frame indices that are not unique and increasing"


def _tum(out: tuple[np.ndarray, np.ndarray], data: bytes) -> None:
    times, poses = out
    _finite(times)
    _kitti_poses(poses, data)


def _extrinsics(table: dict[int, np.ndarray], data: bytes, camera: bool) -> None:
    assert table, "a camera file read as no frames at all"
    rows = _table_rows(data, camera)
    assert len(table) == len(rows), "frames were merged: frame numbers that are not unique"
    assert [float(f) for f in table] == [row[0] for row in rows], "frames not as written"
    assert all(isinstance(f, int) for f in table)
    _rigid(np.stack(list(table.values())))


def _intrinsics(table: dict[int, np.ndarray], data: bytes) -> None:
    assert table, "a camera file read as no frames at all"
    rows = _table_rows(data, camera=True)
    assert len(table) == len(rows), "frames were merged: frame numbers that are not unique"
    K = np.stack(list(table.values()))
    _finite(K)
    assert (K[:, :2] > 0).all(), "a focal length that is not positive"


def _calib(K: np.ndarray, _: bytes) -> tuple[float, ...]:
    assert K.shape == (4,)
    _finite(K)
    assert (K[:2] > 0).all(), "a focal length that is not positive"
    return tuple(K.tolist())


# --------------------------------------------------------------------------------------------
# Valid files of every format, written by the project's own writers (or as the datasets ship)
# --------------------------------------------------------------------------------------------

_RNG = np.random.default_rng(0)
_FLOW = _RNG.normal(0, 3, (6, 9, 2)).astype(np.float32)
_IMAGE = (_RNG.random((6, 9, 3)) * 255).astype(np.uint8)  # B, G, R as cv2 writes it
_POSES = np.tile(np.eye(4), (3, 1, 1))
_POSES[:, :3, :3] = Rotation.from_rotvec([[0, 0, 0], [0, 0.05, 0], [0.01, 0.1, 0]]).as_matrix()
_POSES[:, :3, 3] = [[0, 0, 0], [0.1, 0.0, 0.9], [0.2, 0.01, 1.8]]
_K = np.array([718.856, 718.856, 607.1928, 185.2157])


def _bytes_written_by(write: Callable[[Path], None], suffix: str) -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"f{suffix}"
        write(path)
        return path.read_bytes()


def _npz(path: Path) -> None:
    buf = io.BytesIO()
    np.savez(buf, flow=_FLOW)
    path.write_bytes(buf.getvalue())


def _png8(path: Path) -> None:
    ok, buf = cv2.imencode(".png", _IMAGE)
    assert ok
    path.write_bytes(buf.tobytes())


_HEADER16 = " ".join(f"r{i},{j}" for i in range(1, 5) for j in range(1, 5))
_W2C = np.linalg.inv(_POSES)  # Virtual KITTI stores world-to-camera


def _matrix(m: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in m.ravel())


_TEXT_FILES = {
    "kitti_poses": "".join(
        " ".join(f"{v:.9e}" for v in p[:3].ravel()) + "\n" for p in _POSES
    ).encode(),
    "tum_poses": b"# timestamp tx ty tz qx qy qz qw\n"
    b"0.0 0 0 0 0 0 0 1\n0.1 0.1 0 0.9 0 0.0499792 0 0.9987503\n",
    "times": b"0.000000e+00\n1.036400e-01\n2.072800e-01\n",
    "calib": (
        b"P0: 7.18e+02 0 6.07e+02 0 0 7.18e+02 1.85e+02 0 0 0 1 0\n"
        b"P2: 7.188560e+02 0 6.071928e+02 4.538225e+01 0 7.188560e+02 1.852157e+02 "
        b"-1.130887e-01 0 0 1 3.779761e-03\n"
    ),
    "vkitti1_extrinsics": (
        f"frame {_HEADER16}\n" + "".join(f"{k} {_matrix(m)}\n" for k, m in enumerate(_W2C))
    ).encode(),
    "vkitti2_extrinsics": (
        f"frame cameraID {_HEADER16}\n"
        + "".join(f"{k} {c} {_matrix(m)}\n" for k, m in enumerate(_W2C) for c in (0, 1))
    ).encode(),
    "vkitti2_intrinsics": (
        "frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n"
        + "".join(f"{k} {c} 725.0087 725.0087 620.5 187.0\n" for k in range(3) for c in (0, 1))
    ).encode(),
}

# name → (file suffix, reader, valid file bytes, what a result must mean: check(out, bytes))
READERS: dict[str, tuple[str, Callable[[Path], Any], bytes, Callable[[Any, bytes], Any]]] = {
    "flo": (
        ".flo",
        flow_io.read_flo,
        _bytes_written_by(lambda p: flow_io.write_flo(p, _FLOW), ".flo"),
        lambda out, _: _flow(out),
    ),
    "kitti_flow_png": (
        ".png",
        flow_io.read_kitti_flow_png,
        _bytes_written_by(lambda p: flow_io.write_kitti_flow_png(p, _FLOW), ".png"),
        lambda out, _: _flow(out),
    ),
    "vkitti_flow_png": (
        ".png",
        flow_io.read_vkitti_flow_png,
        _bytes_written_by(lambda p: flow_io.write_vkitti_flow_png(p, _FLOW), ".png"),
        lambda out, _: _flow(out),
    ),
    "vkitti_depth": (
        ".png",
        flow_io.read_vkitti_depth,
        _bytes_written_by(lambda p: flow_io.write_vkitti_depth(p, np.abs(_FLOW[..., 0])), ".png"),
        lambda out, _: _depth(out),
    ),
    "npy_flow": (
        ".npy",
        flow_io.read_npy_flow,
        _bytes_written_by(lambda p: flow_io.write_npy_flow(p, _FLOW), ".npy"),
        lambda out, _: _flow(out),
    ),
    "npz_flow": (
        ".npz",
        flow_io.read_npy_flow,
        _bytes_written_by(_npz, ".npz"),
        lambda out, _: _flow(out),
    ),
    "rgb": (".png", flow_io.read_rgb, _bytes_written_by(_png8, ".png"), lambda out, _: _rgb(out)),
    "image_size": (
        ".png",
        flow_io.image_size,
        _bytes_written_by(_png8, ".png"),
        lambda out, _: _image_size(out),
    ),
    "kitti_poses": (".txt", pose_io.read_kitti_poses, _TEXT_FILES["kitti_poses"], _kitti_poses),
    "kitti_dataset_poses": (
        ".txt",
        kitti_dataset_poses,
        _TEXT_FILES["kitti_poses"],
        _kitti_poses,
    ),
    "tum_poses": (".txt", pose_io.read_tum_poses, _TEXT_FILES["tum_poses"], _tum),
    "auto_poses": (".txt", pose_io.read_poses, _TEXT_FILES["kitti_poses"], _pose_file),
    "kitti_times": (
        ".txt",
        pose_io.read_kitti_times,
        _TEXT_FILES["times"],
        lambda out, data: (_finite(out), len(out) == len(_pose_rows(data)) or _fail()),
    ),
    "kitti_calib": (".txt", read_kitti_calib, _TEXT_FILES["calib"], _calib),
    "vkitti1_extrinsics": (
        ".txt",
        lambda p: read_vkitti_extrinsics(p, 1),
        _TEXT_FILES["vkitti1_extrinsics"],
        lambda out, data: _extrinsics(out, data, camera=False),
    ),
    "vkitti2_extrinsics": (
        ".txt",
        lambda p: read_vkitti_extrinsics(p, 2),
        _TEXT_FILES["vkitti2_extrinsics"],
        lambda out, data: _extrinsics(out, data, camera=True),
    ),
    "vkitti2_intrinsics": (
        ".txt",
        read_vkitti_intrinsics,
        _TEXT_FILES["vkitti2_intrinsics"],
        _intrinsics,
    ),
}

# What each valid file holds, read back: the test's own expectation, not the property's.
_QUANTUM_VKITTI = (9 - 1) / 65535  # half a 16-bit step of the Virtual KITTI flow encoding
VALID_CONTENTS: dict[str, Callable[[Any], None]] = {
    "flo": lambda out: np.testing.assert_array_equal(out[0], _FLOW),
    "kitti_flow_png": lambda out: np.testing.assert_allclose(out[0], _FLOW, atol=0.5 / 64),
    "vkitti_flow_png": lambda out: np.testing.assert_allclose(  # its range: ±(W − 1, H − 1)
        out[0], np.clip(_FLOW, [-8, -5], [8, 5]), atol=_QUANTUM_VKITTI + 1e-6
    ),
    "vkitti_depth": lambda out: np.testing.assert_allclose(
        out[0], np.abs(_FLOW[..., 0]), atol=0.005 + 1e-6
    ),
    "npy_flow": lambda out: np.testing.assert_array_equal(out[0], _FLOW),
    "npz_flow": lambda out: np.testing.assert_array_equal(out[0], _FLOW),
    "rgb": lambda out: np.testing.assert_array_equal(out, _IMAGE[..., ::-1]),
    "image_size": lambda out: out == (6, 9) or _fail(),
    "kitti_poses": lambda out: np.testing.assert_allclose(out, _POSES, rtol=0, atol=1e-9),
    "kitti_dataset_poses": lambda out: np.testing.assert_allclose(out, _POSES, atol=1e-9),
    "auto_poses": lambda out: np.testing.assert_allclose(out.poses, _POSES, atol=1e-9),
    "tum_poses": lambda out: (
        np.testing.assert_array_equal(out[0], [0.0, 0.1]),
        np.testing.assert_allclose(out[1][1, :3, 3], [0.1, 0, 0.9]),
        np.testing.assert_allclose(
            Rotation.from_matrix(out[1][1, :3, :3]).as_rotvec(), [0, 0.1, 0], atol=1e-6
        ),
    ),
    "kitti_times": lambda out: np.testing.assert_array_equal(out, [0.0, 0.10364, 0.20728]),
    "kitti_calib": lambda out: np.testing.assert_array_equal(out, _K),
    "vkitti1_extrinsics": lambda out: np.testing.assert_array_equal(
        np.stack([out[k] for k in range(3)]), _W2C
    ),
    "vkitti2_extrinsics": lambda out: np.testing.assert_array_equal(
        np.stack([out[k] for k in range(3)]), _W2C
    ),
    "vkitti2_intrinsics": lambda out: np.testing.assert_array_equal(
        np.stack([out[k] for k in range(3)]), np.tile([725.0087, 725.0087, 620.5, 187.0], (3, 1))
    ),
}


def _fail() -> None:
    raise AssertionError("a reader returned a malformed result")


# --------------------------------------------------------------------------------------------
# Reading a file: refused with the project's error naming it, or meaningful
# --------------------------------------------------------------------------------------------


def _read(name: str, data: bytes, reader: Callable[[Path], Any] | None = None) -> Any:
    """Write ``data`` and read it with reader ``name``: None if refused with the project's
    error naming the file (and, for a text file, its line), else what the check made of it."""
    suffix, default, _, check = READERS[name]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"input_{name}{suffix}"
        path.write_bytes(data)
        try:
            out = (reader or default)(path)
        except PROJECT_ERRORS as err:
            message = str(err)
            assert path.name in message, f"the error does not name the file: {message}"
            assert "\n" not in message, f"not one line: {message}"
            if suffix == ".txt" and re.match(rf"{re.escape(str(path))}:\d+: ", message) is None:
                # a text file's problem names its line, unless it is the file as a whole
                assert re.search(r"not UTF-8|not a text file|no 'P2:'", message), message
            return None
        return check(out, data)


@pytest.mark.parametrize("name", sorted(READERS))
def test_valid_files_read(name: str) -> None:
    """The uncorrupted files read back as what was written (within each format's precision),
    and what they hold passes the properties the fuzzing below checks."""
    suffix, reader, valid, check = READERS[name]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"valid{suffix}"
        path.write_bytes(valid)
        out = reader(path)
    VALID_CONTENTS[name](out)
    check(out, valid)


# --------------------------------------------------------------------------------------------
# Garbled bytes and tokens
# --------------------------------------------------------------------------------------------

# Tokens that break numeric text in the ways real files break: non-finite or overflowing
# numbers, stray characters, encoding garbage, absurd lengths.
_BAD_TOKENS = st.sampled_from(
    ["nan", "inf", "-inf", "1e999", "-1e999", "", "x", "1,5", "0x10", "\x00", "\xff\xfe", "9" * 400,
     "1e308", "-0", "3.4.5", "#", "\t", "P2:", "\r", "0", "5", "2.5", "-1"]
)  # fmt: skip


@st.composite
def corrupted(draw: st.DrawFn, valid: bytes) -> bytes:
    """Random bytes, ``valid`` cut short, ``valid`` with bytes overwritten, or (text) with a
    token replaced, a line dropped, doubled on itself or repeated (a duplicate row)."""
    kind = draw(st.sampled_from(["random", "truncate", "flip", "token", "lines"]))
    if kind == "random":
        return draw(st.binary(max_size=2 * len(valid)))
    if kind == "truncate":
        return valid[: draw(st.integers(0, max(0, len(valid) - 1)))]
    if kind == "flip":
        data = bytearray(valid)
        for _ in range(draw(st.integers(1, 8))):
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
        return bytes(data)
    lines = valid.split(b"\n")
    i = draw(st.integers(0, len(lines) - 1))
    if kind == "lines":
        how = draw(st.sampled_from(["drop", "double", "repeat"]))
        if how == "drop":
            del lines[i]
        elif how == "double":
            lines.insert(i, lines[i] + b" " + lines[i])
        else:
            lines.insert(i, lines[i])
        return b"\n".join(lines)
    tokens = lines[i].split(b" ") or [b""]
    j = draw(st.integers(0, len(tokens) - 1))
    tokens[j] = draw(_BAD_TOKENS).encode("utf-8", "surrogateescape")
    lines[i] = b" ".join(tokens)
    return b"\n".join(lines)


@pytest.mark.parametrize("name", sorted(READERS))
@FUZZ
@given(data=st.data())
def test_corrupt_files_are_refused_naming_the_file_or_read_as_they_mean(name: str, data) -> None:
    _read(name, data.draw(corrupted(READERS[name][2]), label="file bytes"))


@pytest.mark.parametrize("name", ["flo", "npy_flow", "kitti_poses", "tum_poses", "kitti_calib"])
def test_missing_and_unreadable_files_raise_the_projects_error(name: str, tmp_path: Path) -> None:
    suffix, reader, _, _ = READERS[name]
    missing = tmp_path / f"missing{suffix}"
    with pytest.raises(PROJECT_ERRORS, match=missing.name):
        reader(missing)
    directory = tmp_path / f"a_directory{suffix}"
    directory.mkdir()
    with pytest.raises(PROJECT_ERRORS, match=directory.name) as err:
        reader(directory)
    assert "not found" not in str(err.value)  # a directory is there: it is not a file


# --------------------------------------------------------------------------------------------
# Header fields: sizes, shapes and dtypes
# --------------------------------------------------------------------------------------------

# Sizes from the plausible to the absurd: small ones are written whole, large ones as a header
# with a few bytes of data (what a corrupt or hostile file is).
_SIDES = st.one_of(st.integers(1, 24), st.integers(1, 70_000), st.sampled_from([30_000, 65_535]))


@st.composite
def png_files(draw: st.DrawFn) -> tuple[tuple[int, int], bytes]:
    """``((height, width), bytes)`` of a PNG with drawn size, bit depth and channels."""
    height, width = draw(_SIDES, label="height"), draw(_SIDES, label="width")
    depth = draw(st.sampled_from([8, 16]), label="bit depth")
    channels = draw(st.sampled_from([1, 3, 4]), label="channels")
    if height * width <= 24 * 24:
        dtype = np.uint16 if depth == 16 else np.uint8
        pixels = np.full((height, width, channels), draw(st.integers(0, 255)), dtype)
        ok, buf = cv2.imencode(".png", pixels)
        assert ok
        return (height, width), buf.tobytes()
    return (height, width), png_header_only(width, height, depth, channels)


_PNG_READERS = ["kitti_flow_png", "vkitti_flow_png", "vkitti_depth", "rgb", "image_size"]
_SIZE_OF = {
    "kitti_flow_png": _flow,
    "vkitti_flow_png": _flow,
    "vkitti_depth": _depth,
    "rgb": _rgb,
    "image_size": _image_size,
}


@pytest.mark.parametrize("name", _PNG_READERS)
@HEADERS
@given(png=png_files())
def test_png_headers_of_any_size_are_refused_or_read_at_that_size(name: str, png) -> None:
    """A header claiming 30,000 × 30,000 made OpenCV try 5.4 GB and raise cv2.error."""
    claimed, data = png
    assert _read(name, data) in (None, claimed)


def jpeg_claiming(height: int, width: int) -> bytes:
    """A small JPEG whose start-of-frame header claims ``height × width``."""
    ok, buf = cv2.imencode(".jpg", np.full((8, 8, 3), 128, np.uint8))
    assert ok
    data = bytearray(buf.tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


@HEADERS
@given(height=st.integers(1, 65_535), width=st.integers(1, 65_535))
def test_jpeg_headers_of_any_size_are_refused_or_read_at_that_size(height, width) -> None:
    data = jpeg_claiming(height, width)
    for name in ("rgb", "image_size"):
        assert _read(name, data) in (None, (height, width))


@st.composite
def npy_files(draw: st.DrawFn) -> tuple[tuple[int, ...], bytes]:
    """``(shape, bytes)`` of a ``.npy`` whose header has a drawn shape and dtype, with
    all its data (small shapes, sometimes short by a few bytes) or a few bytes (large ones)."""
    height = draw(st.one_of(st.integers(0, 12), st.integers(0, 200_000)), label="height")
    width = draw(st.one_of(st.integers(0, 12), st.integers(0, 200_000)), label="width")
    layout = draw(st.sampled_from(["HW2", "2HW", "HWC"]), label="layout")
    shape = {
        "HW2": (height, width, 2),
        "2HW": (2, height, width),
        "HWC": (height, width, draw(st.integers(1, 4))),
    }[layout]
    dtype = np.dtype(draw(st.sampled_from(["<f4", "<f8", "<f2", ">f4", "<i4"]), label="dtype"))
    size = int(np.prod(shape)) * dtype.itemsize
    if size <= 12 * 12 * 2 * 8:
        size = max(size - draw(st.sampled_from([0, 0, 0, 1, 8]), label="bytes short"), 0)
        return shape, npy_header_only(
            shape, dtype.str, draw(st.binary(min_size=size, max_size=size))
        )
    return shape, npy_header_only(shape, dtype.str)


def _npz_of(npy: bytes) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as archive:
        archive.writestr("flow.npy", npy)
    return buf.getvalue()


@pytest.mark.parametrize("name", ["npy_flow", "npz_flow"])
@HEADERS
@given(npy=npy_files())
def test_npy_headers_of_any_shape_are_refused_or_read_as_that_flow(name: str, npy) -> None:
    """A header claiming (1e5, 1e5, 2) raised an uncaught MemoryError (149 GiB)."""
    shape, data = npy
    got = _read(name, _npz_of(data) if name == "npz_flow" else data)
    assert got in (None, shape[:2] if shape[2] == 2 else shape[1:])


@HEADERS
@given(
    width=st.one_of(st.integers(-3, 24), st.integers(-(2**31), 2**31 - 1)),
    height=st.one_of(st.integers(-3, 24), st.integers(-(2**31), 2**31 - 1)),
    short=st.sampled_from([0, 0, 4]),
)
def test_flo_headers_of_any_size_are_refused_or_read_at_that_size(width, height, short) -> None:
    header = np.array([flow_io.FLO_MAGIC], "<f4").tobytes() + struct.pack("<ii", width, height)
    n = 8 * width * height if 0 < width * height <= 24 * 24 else 64
    assert _read("flo", header + b"\0" * (n - short)) in (None, (height, width))


# --------------------------------------------------------------------------------------------
# Header fields: poses, frame numbers and cameras
# --------------------------------------------------------------------------------------------

# A rotation block as written: a rotation, or one scaled (by 5: the Virtual KITTI file of
# issue 74), mirrored, shrunk or rounded past a text file's precision.
_SCALES = st.sampled_from([1.0, 1.0, 1.0, 1.0, 5.0, 0.2, -1.0, 0.0, 1.001, 1.05])
_QUATERNIONS = st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4).filter(
    lambda q: np.linalg.norm(q) > 0.1
)
_TRANSLATIONS = st.tuples(*[st.floats(-100, 100, allow_nan=False)] * 3)


@st.composite
def frame_numbers(draw: st.DrawFn, n: int) -> list[float]:
    """``n`` frame numbers: mostly 0, 1, 2, …, else with a duplicate, a gap, a fraction or a
    step back."""
    frames = [float(k) for k in range(n)]
    kind = draw(st.sampled_from(["plain", "plain", "gap", "duplicate", "fraction", "back"]))
    i = draw(st.integers(0, n - 1))
    if kind == "gap":
        frames = [f + (3 if k >= i else 0) for k, f in enumerate(frames)]
    elif kind == "duplicate" and i > 0:
        frames[i] = frames[i - 1]
    elif kind == "fraction":
        frames[i] += 0.5
    elif kind == "back" and i > 0:
        frames[i - 1], frames[i] = frames[i], frames[i - 1]
    return frames


@st.composite
def poses_as_written(draw: st.DrawFn) -> tuple[list[float], np.ndarray]:
    """``(frame numbers, (N, 4, 4) matrices)``: drawn rotations (some blocks scaled) and
    translations, a bottom row that is sometimes not ``0 0 0 1``."""
    n = draw(st.integers(1, 5), label="rows")
    mats = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        mats[k, :3, :3] = Rotation.from_quat(draw(_QUATERNIONS)).as_matrix()
        mats[k, :3, :3] *= draw(_SCALES, label="rotation scale")
        mats[k, :3, 3] = draw(_TRANSLATIONS)
        mats[k, 3, 2] = draw(st.sampled_from([0.0, 0.0, 0.0, 0.5]), label="bottom row")
    return draw(frame_numbers(n), label="frames"), mats


@HEADERS
@given(written=poses_as_written(), indexed=st.booleans())
def test_kitti_poses_are_refused_or_rigid_with_unique_frames(written, indexed) -> None:
    frames, mats = written
    text = "".join(
        (f"{frame!r} " if indexed else "") + " ".join(repr(float(v)) for v in m[:3].ravel()) + "\n"
        for frame, m in zip(frames, mats, strict=True)
    )
    for name in ("kitti_poses", "kitti_dataset_poses", "auto_poses"):
        _read(name, text.encode())


@HEADERS
@given(
    quaternions=st.lists(_QUATERNIONS, min_size=1, max_size=4),
    norm=st.sampled_from([1.0, 1.0, 1.004, 0.5, 2.0, 0.0]),
    translation=_TRANSLATIONS,
)
def test_tum_poses_are_refused_or_rigid(quaternions, norm, translation) -> None:
    lines = []
    for k, q in enumerate(quaternions):
        unit = np.asarray(q) / np.linalg.norm(q)
        lines.append(" ".join(map(repr, [k / 10, *translation, *(unit * norm).tolist()])))
    _read("tum_poses", ("\n".join(lines) + "\n").encode())


@pytest.mark.parametrize("version", [1, 2])
@HEADERS
@given(written=poses_as_written())
def test_vkitti_extrinsics_are_refused_or_rigid_with_unique_frames(version, written) -> None:
    """Frame 2's rotation scaled by 5 passed, and duplicate or fractional frames were merged
    by ``int(frame)``."""
    frames, mats = written
    if version == 1:
        text = f"frame {_HEADER16}\n" + "".join(
            f"{frame!r} {_matrix(m)}\n" for frame, m in zip(frames, mats, strict=True)
        )
    else:
        text = f"frame cameraID {_HEADER16}\n" + "".join(
            f"{frame!r} {camera} {_matrix(m)}\n"
            for frame, m in zip(frames, mats, strict=True)
            for camera in (0, 1)
        )
    _read(f"vkitti{version}_extrinsics", text.encode())


_FOCAL = st.one_of(
    st.floats(1, 2000), st.sampled_from([0.0, -0.0, -725.0, 1e-300]), st.floats(-10, 10)
)


@HEADERS
@given(fx=_FOCAL, fy=_FOCAL, cx=st.floats(-100, 1500), cy=st.floats(-100, 500), n=st.integers(1, 4))
def test_intrinsics_are_refused_or_have_positive_focal_lengths(fx, fy, cx, cy, n) -> None:
    """``fx = 0`` passed ``read_kitti_calib`` and ``data.check``; training failed late."""
    calib = f"P2: {fx!r} 0 {cx!r} 45.38 0 {fy!r} {cy!r} -0.113 0 0 1 0.0038\n"
    _read("kitti_calib", calib.encode())
    rows = "".join(f"{k} {c} {fx!r} {fy!r} {cx!r} {cy!r}\n" for k in range(n) for c in (0, 1))
    _read("vkitti2_intrinsics", f"frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n{rows}".encode())
    # with the image size the principal point must lie inside the image too
    got = _read("kitti_calib", calib.encode(), lambda p: read_kitti_calib(p, (375, 1242)))
    if got is not None:
        assert 0 <= got[2] <= 1242 and 0 <= got[3] <= 375, "a principal point outside the image"


# --------------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------------


class _RunsCode:
    """A pickle payload: unpickling it writes ``marker`` (``Path.write_text``)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (self.marker, "the checkpoint ran code"))


def _checkpoint_bytes(extra: dict | None = None) -> bytes:
    buf = io.BytesIO()
    config = {"net": {"hidden_units": 4, "height": 2, "width": 2}}
    torch.save(
        {"state_dict": {"w": torch.arange(4.0)}, "mfg_model_config": config, **(extra or {})}, buf
    )
    return buf.getvalue()


_CHECKPOINT = _checkpoint_bytes()


@st.composite
def checkpoint_files(draw: st.DrawFn, marker: Path) -> tuple[str, bytes]:
    """``(what it is, bytes)``: ``"whole"``, ``"random"`` bytes, ``"corrupt"`` (a checkpoint
    cut short), ``"garbled"`` (a checkpoint with bytes overwritten: it may still load) or
    ``"unsafe"`` (a pickle, bare or inside a checkpoint, that would write ``marker``)."""
    kind = draw(st.sampled_from(["whole", "random", "truncate", "flip", "pickle", "zip_pickle"]))
    if kind == "whole":
        return "whole", _CHECKPOINT
    if kind == "random":
        return "random", draw(st.binary(min_size=1, max_size=400))
    if kind == "truncate":
        return "corrupt", _CHECKPOINT[: draw(st.integers(1, len(_CHECKPOINT) - 1))]
    if kind == "flip":
        data = bytearray(_CHECKPOINT)
        for _ in range(draw(st.integers(1, 4))):
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
        return "garbled", bytes(data)
    if kind == "pickle":
        protocol = draw(st.integers(0, pickle.HIGHEST_PROTOCOL), label="protocol")
        return "unsafe", pickle.dumps({"state_dict": _RunsCode(marker)}, protocol=protocol)
    return "unsafe", _checkpoint_bytes({"payload": _RunsCode(marker)})


@HEADERS
@given(data=st.data())
def test_checkpoints_load_or_are_called_corrupt_or_unsafe_and_nothing_runs(data) -> None:
    """Random bytes were described as a file that "holds Python objects … could run code"."""
    with tempfile.TemporaryDirectory() as tmp:
        marker = Path(tmp) / "marker.txt"
        kind, payload = data.draw(checkpoint_files(marker), label="checkpoint")
        path = Path(tmp) / "model.ckpt"
        path.write_bytes(payload)
        try:
            ckpt = load_checkpoint(path)
        except CheckpointError as err:
            message = str(err)
            assert str(path) in message and "\n" not in message, message
            said = {"corrupt", "unsafe"} & set(re.findall(r"\b(corrupt|unsafe)\b", message))
            if kind == "garbled" and not said:  # it still loads, but lost a key of its own
                assert "not a Lightning checkpoint" in message or "mfg_lightning.train" in message
                return
            assert len(said) == 1, f"neither or both of corrupt and unsafe: {message}"
            # random bytes that happen to pickle a global are unsafe too; a garbled checkpoint
            # is either
            if kind not in ("garbled", "random"):
                assert said == {kind}, f"a {kind} checkpoint called: {message}"
        else:
            assert kind in ("whole", "garbled"), f"a {kind} file was loaded as a checkpoint"
            assert set(ckpt) >= {"state_dict", "mfg_model_config"}
        assert not marker.exists(), "reading the checkpoint ran its code"


# --------------------------------------------------------------------------------------------
# What Hypothesis found, kept
# --------------------------------------------------------------------------------------------

#: file in tests/data/fuzz_regressions → (reader, words its one-line error must hold). Each is
#: what Hypothesis found (shrunk) running these properties against the readers before they
#: checked meaning and sizes (the main branch at 1528239): every one was read without an error,
#: or crashed the reader outside the project's errors (cv2.error, MemoryError, a torch message
#: saying neither corrupt nor unsafe). The PNGs and .npy files are headers with a few bytes.
REGRESSION_FILES: dict[str, tuple[Callable[[Path], Any], str]] = {
    # read: a rotation block scaled by 5, a reflection, a bottom row 0 0 0.5 1, frame 0.5
    "vkitti_1.3.1_extrinsics_rotation_scaled_by_5.txt": (
        lambda p: read_vkitti_extrinsics(p, 1),
        ":2: the 3×3 block is not a rotation (max |RᵀR − I| = 24, det = 125;",
    ),
    "vkitti_1.3.1_extrinsics_mirrored.txt": (
        lambda p: read_vkitti_extrinsics(p, 1),
        ":2: the 3×3 block is not a rotation (max |RᵀR − I| = 0, det = -1;",
    ),
    "vkitti_1.3.1_extrinsics_bottom_row.txt": (
        lambda p: read_vkitti_extrinsics(p, 1),
        ":2: the bottom row is 0 0 0.5 1, not 0 0 0 1",
    ),
    "vkitti_1.3.1_extrinsics_fractional_frame.txt": (
        lambda p: read_vkitti_extrinsics(p, 1),
        ":2: frame 0.5 is not a whole number >= 0",
    ),
    # read as 2 frames: camera 0's frame 1 twice, merged by int(frame)
    "vkitti_2.0.3_extrinsic_duplicate_frame.txt": (
        lambda p: read_vkitti_extrinsics(p, 2),
        ":6: frame 1 does not follow 1 (line 4): frame numbers must be unique and increasing",
    ),
    # read: focal lengths of 0
    "vkitti_2.0.3_intrinsic_fx_0.txt": (
        read_vkitti_intrinsics,
        ":2: focal lengths must be positive, got fx = 0, fy = 1",
    ),
    "kitti_calib_fy_0.txt": (
        read_kitti_calib,
        ":1: P2: focal lengths must be positive, got fx = 1, fy = 0",
    ),
    # cv2.error (pixels <= CV_IO_MAX_IMAGE_PIXELS) escaped the reader
    "png16_header_35795x29997.png": (
        flow_io.read_kitti_flow_png,
        "the header claims 35795×29997 pixels, more than the 33,554,432",
    ),
    "png8_header_65533x16385.png": (
        flow_io.read_rgb,
        "the header claims 65533×16385 pixels, more than the 33,554,432",
    ),
    # image_size returned 1027 × 32673, beyond the bound
    "png8_header_32673x1027.png": (
        flow_io.image_size,
        "the header claims 32673×1027 pixels, more than the 33,554,432",
    ),
    # MemoryError (8.06 GiB; the (1e5, 1e5, 2): 149 GiB), and an empty flow read
    "npy_header_1866x144945x4_float64.npy": (
        flow_io.read_npy_flow,
        "flow must be (2, H, W) or (H, W, 2), got (1866, 144945, 4)",
    ),
    "npy_header_100000x100000x2.npy": (
        flow_io.read_npy_flow,
        "the header claims 100000×100000 pixels, more than the 33,554,432",
    ),
    "npy_header_0x0x2.npy": (flow_io.read_npy_flow, "the header claims an empty 0×0 image"),
    # "holds Python objects … could run code", and torch's zip reader's own words
    "random_bytes.ckpt": (load_checkpoint, "is corrupt: not a readable checkpoint"),
    "zip_signature_only.ckpt": (load_checkpoint, "is corrupt: not a readable checkpoint"),
}


@pytest.mark.parametrize("name", sorted(REGRESSION_FILES))
def test_inputs_hypothesis_found_are_refused_in_one_line_naming_the_file(name: str) -> None:
    read, words = REGRESSION_FILES[name]
    path = REGRESSIONS / name
    with pytest.raises((*PROJECT_ERRORS, CheckpointError)) as err:
        read(path)
    message = str(err.value)
    assert str(path) in message and words in message and "\n" not in message, message


def test_every_regression_file_is_read() -> None:
    assert sorted(p.name for p in REGRESSIONS.iterdir()) == sorted(REGRESSION_FILES)


# --------------------------------------------------------------------------------------------
# Corrupt batches through a real training step
# --------------------------------------------------------------------------------------------

H, W, B = 32, 64, 2


@functools.lru_cache(maxsize=1)
def _clean_batch() -> dict[str, Any]:
    dm = SyntheticDataModule(
        height=H, width=W, train_sequences=1, test_sequences=1, sequence_length=6, val_fraction=0.2
    )
    return collate_samples([dm.dataset("train")[i] for i in range(B)])


def _copy(batch: dict[str, Any]) -> dict[str, Any]:
    return {k: v.clone() if isinstance(v, torch.Tensor) else list(v) for k, v in batch.items()}


_VALUES = st.sampled_from(
    [float("nan"), float("inf"), -float("inf"), 3.0e38, -3.0e38, 1e30, 1e20, 1e10, 0.0, -1e-30]
)


@st.composite
def corrupt_batches(draw: st.DrawFn) -> dict[str, Any]:
    """A synthetic batch with one or two corruptions: extreme or non-finite values in a random
    region of flow, pose, intrinsics or depth, or a tensor of the wrong shape or dtype."""
    batch = _copy(_clean_batch())
    for _ in range(draw(st.integers(1, 2))):
        kind = draw(st.sampled_from(["values", "values", "values", "shape", "dtype"]))
        key = draw(st.sampled_from(["flow", "pose", "intrinsics", "depth", "flow_valid"]))
        t = batch[key]
        if kind == "values" and t.dtype.is_floating_point and t.numel():  # (not emptied above)
            region = tuple(
                slice(draw(st.integers(0, n - 1)), draw(st.integers(1, n))) for n in t.shape
            )
            t[region] = draw(_VALUES)
        elif kind == "shape":
            dim = draw(st.integers(0, t.ndim - 1))
            size = draw(st.sampled_from([0, 1, 3, t.shape[dim] + 1]))
            if size <= t.shape[dim]:
                batch[key] = t.narrow(dim, 0, size)
            else:
                batch[key] = torch.cat([t, t.narrow(dim, 0, 1)], dim)
            if draw(st.booleans()):
                batch[key] = batch[key].unsqueeze(0)
        elif kind == "dtype":
            batch[key] = t.to(draw(st.sampled_from([torch.float64, torch.float16, torch.int32])))
    return batch


def _module() -> MFGLitModule:
    torch.manual_seed(0)
    net = MFG(height=H, width=W, hidden_units=32, channels=(8, 8, 8, 16, 16))
    return MFGLitModule(
        net,
        MFGLoss(w_s=100.0),
        functools.partial(torch.optim.Adam, lr=1e-3),
        image_log_every_n_steps=0,
        max_consecutive_nonfinite=2,
    )


@FUZZ
@given(batch=corrupt_batches())
def test_corrupt_batches_are_refused_or_masked_and_never_reach_the_weights(batch) -> None:
    model = _module()
    # Two steps on the same corrupt batch: the second one would see what the first did.
    loader = torch.utils.data.DataLoader([batch, batch], batch_size=None, collate_fn=lambda b: b)
    trainer = quiet_trainer(max_steps=2, limit_val_batches=0, callbacks=[AgreedSteps()])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            trainer.fit(model, train_dataloaders=loader)
        except SampleError as err:
            # Refused where it entered, naming the samples of the batch.
            assert "synthetic/" in str(err)
        except NonFiniteLossError as err:
            # Every step's loss was non-finite (e.g. a NaN pose): stopped, naming the samples.
            assert "synthetic/" in str(err)
    for name, p in model.named_parameters():
        assert torch.isfinite(p).all(), f"non-finite weight {name}"


@pytest.fixture(autouse=True)
def _quiet() -> Any:
    """Lightning's info lines and the module's masking warnings, once per example, are noise."""
    loggers = [logging.getLogger(n) for n in ("lightning", "lightning.pytorch", "mfg_lightning")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    yield
    for lg, level in zip(loggers, levels, strict=True):
        lg.setLevel(level)
