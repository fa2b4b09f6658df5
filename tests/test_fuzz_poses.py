"""Property-based tests (hypothesis) of the pose and camera readers on fields drawn by the
strategies: rotations (some scaled, mirrored or rounded), translations, frame numbers (with a
duplicate, a gap, a fraction or a step back), quaternion norms and focal lengths. Each reader
refuses the file with the project's one-line data error naming the file and line, or returns
rigid poses with unique frames and positive focal lengths."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from fuzz_readers import _HEADER16, HEADERS, _matrix, _read
from mfg_lightning.data.kitti import read_kitti_calib

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
