"""What the property-based tests of the readers share (tests/test_fuzz*.py): the Hypothesis
settings, what a reader's result must mean, a valid file of every format, the readers by name
and :func:`_read`, which writes bytes and reads them back.

What a result must mean, for every reader: a pose is a rigid transform (``RᵀR = I``,
``det R = +1``, bottom row ``0 0 0 1``, within the readers' stated
:data:`~mfg_lightning.core.data_errors.RIGID_TOLERANCE`); focal lengths are positive; frame
numbers are unique (as many poses come back as the file has rows); an image or flow field has the
size its header claims, within :data:`~mfg_lightning.flow.io.MAX_PIXELS`.
"""

from __future__ import annotations

import io
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from hypothesis import HealthCheck, settings
from scipy.spatial.transform import Rotation

from mfg_lightning.core.data_errors import RIGID_TOLERANCE, DataFileError
from mfg_lightning.data.kitti import read_kitti_calib
from mfg_lightning.data.kitti import read_kitti_poses_as_data_file as kitti_dataset_poses
from mfg_lightning.data.vkitti_files import read_vkitti_extrinsics, read_vkitti_intrinsics
from mfg_lightning.flow import io as flow_io
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


def _flow_format(
    suffix: str, read: Callable[[Path], Any], write: Callable[[Path, np.ndarray], None]
) -> tuple[str, Callable[[Path], Any], bytes, Callable[[Any, bytes], Any]]:
    """A flow format's entry of :data:`READERS`: its reader, ``_FLOW`` as its writer writes it,
    and the flow field's check."""
    return (
        suffix,
        read,
        _bytes_written_by(lambda p: write(p, _FLOW), suffix),
        lambda out, _: _flow(out),
    )


# name → (file suffix, reader, valid file bytes, what a result must mean: check(out, bytes))
READERS: dict[str, tuple[str, Callable[[Path], Any], bytes, Callable[[Any, bytes], Any]]] = {
    "flo": _flow_format(".flo", flow_io.read_flo, flow_io.write_flo),
    "kitti_flow_png": _flow_format(
        ".png", flow_io.read_kitti_flow_png, flow_io.write_kitti_flow_png
    ),
    "vkitti_flow_png": _flow_format(
        ".png", flow_io.read_vkitti_flow_png, flow_io.write_vkitti_flow_png
    ),
    "vkitti_depth": (
        ".png",
        flow_io.read_vkitti_depth,
        _bytes_written_by(lambda p: flow_io.write_vkitti_depth(p, np.abs(_FLOW[..., 0])), ".png"),
        lambda out, _: _depth(out),
    ),
    "npy_flow": _flow_format(".npy", flow_io.read_npy_flow, flow_io.write_npy_flow),
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
