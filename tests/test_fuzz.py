"""Property-based tests (hypothesis): corrupt files and corrupt batches never crash deep inside
numpy, OpenCV or torch and never reach the weights.

Every file reader, fed random bytes, a valid file cut short, or a valid file with bytes or
tokens garbled, either returns well-formed finite arrays or raises the project's own error
(:class:`DataFileError` / :class:`PoseFileError`, both ``ValueError``) naming the file. Every
corrupt batch pushed through a real ``Trainer.fit`` of the module is either refused with a
:class:`SampleError` naming its samples, or masked / skipped so that every weight stays finite.
"""

from __future__ import annotations

import functools
import io
import logging
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import quiet_trainer
from mfg_lightning.core.data_errors import DataFileError
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
from mfg_lightning.trajectory import pose_io
from mfg_lightning.trajectory.pose_io import PoseFileError

FUZZ = settings(
    max_examples=40,
    deadline=None,
    derandomize=True,  # the same examples on every run: a deterministic suite
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
PROJECT_ERRORS = (DataFileError, PoseFileError)

# --------------------------------------------------------------------------------------------
# Valid files of every format, written by the project's own writers (or as the datasets ship)
# --------------------------------------------------------------------------------------------

_RNG = np.random.default_rng(0)
_FLOW = _RNG.normal(0, 3, (6, 9, 2)).astype(np.float32)
_POSES = np.tile(np.eye(4), (3, 1, 1))
_POSES[:, :3, 3] = [[0, 0, 0], [0.1, 0.0, 0.9], [0.2, 0.01, 1.8]]


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
    import cv2

    ok, buf = cv2.imencode(".png", (_RNG.random((6, 9, 3)) * 255).astype(np.uint8))
    assert ok
    path.write_bytes(buf.tobytes())


_MATRIX = " ".join(f"{v:.6e}" for v in np.eye(4).ravel())
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
        "frame "
        + " ".join(f"r{i},{j}" for i in range(1, 5) for j in range(1, 5))
        + "\n"
        + "".join(f"{k} {_MATRIX}\n" for k in range(3))
    ).encode(),
    "vkitti2_extrinsics": (
        "frame cameraID "
        + " ".join(f"r{i},{j}" for i in range(1, 5) for j in range(1, 5))
        + "\n"
        + "".join(f"{k} {c} {_MATRIX}\n" for k in range(3) for c in (0, 1))
    ).encode(),
    "vkitti2_intrinsics": (
        "frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n"
        + "".join(f"{k} {c} 725.0087 725.0087 620.5 187.0\n" for k in range(3) for c in (0, 1))
    ).encode(),
}


def _finite(*arrays: np.ndarray) -> None:
    for a in arrays:
        assert np.isfinite(a).all(), "a reader returned non-finite numbers"


def _check_flow(out: tuple[np.ndarray, np.ndarray]) -> None:
    flow, valid = out
    assert flow.dtype == np.float32 and flow.ndim == 3 and flow.shape[2] == 2
    assert valid.dtype == bool and valid.shape == flow.shape[:2]
    _finite(flow)  # unknown or non-finite pixels are masked: flow 0, valid False


def _check_poses(poses: np.ndarray) -> None:
    assert poses.ndim == 3 and poses.shape[1:] == (4, 4) and len(poses) >= 1
    _finite(poses)


def _check_matrices(table: dict[int, np.ndarray], shape: tuple[int, ...]) -> None:
    for frame, m in table.items():
        assert isinstance(frame, int) and m.shape == shape
        _finite(m)


# name → (file suffix, reader, valid file bytes, check of a successful result)
READERS: dict[str, tuple[str, Callable[[Path], Any], bytes, Callable[[Any], None]]] = {
    "flo": (
        ".flo",
        flow_io.read_flo,
        _bytes_written_by(lambda p: flow_io.write_flo(p, _FLOW), ".flo"),
        _check_flow,
    ),
    "kitti_flow_png": (
        ".png",
        flow_io.read_kitti_flow_png,
        _bytes_written_by(lambda p: flow_io.write_kitti_flow_png(p, _FLOW), ".png"),
        _check_flow,
    ),
    "vkitti_flow_png": (
        ".png",
        flow_io.read_vkitti_flow_png,
        _bytes_written_by(lambda p: flow_io.write_vkitti_flow_png(p, _FLOW), ".png"),
        _check_flow,
    ),
    "vkitti_depth": (
        ".png",
        flow_io.read_vkitti_depth,
        _bytes_written_by(lambda p: flow_io.write_vkitti_depth(p, np.abs(_FLOW[..., 0])), ".png"),
        lambda out: _finite(out[0]),
    ),
    "npy_flow": (
        ".npy",
        flow_io.read_npy_flow,
        _bytes_written_by(lambda p: flow_io.write_npy_flow(p, _FLOW), ".npy"),
        _check_flow,
    ),
    "npz_flow": (".npz", flow_io.read_npy_flow, _bytes_written_by(_npz, ".npz"), _check_flow),
    "rgb": (
        ".png",
        flow_io.read_rgb,
        _bytes_written_by(_png8, ".png"),
        lambda out: (out.dtype == np.uint8 and out.ndim == 3 and out.shape[2] == 3) or _fail(),
    ),
    "image_size": (
        ".png",
        flow_io.image_size,
        _bytes_written_by(_png8, ".png"),
        lambda out: all(isinstance(v, int) and v >= 0 for v in out) or _fail(),
    ),
    "kitti_poses": (".txt", pose_io.read_kitti_poses, _TEXT_FILES["kitti_poses"], _check_poses),
    "kitti_dataset_poses": (
        ".txt",
        kitti_dataset_poses,
        _TEXT_FILES["kitti_poses"],
        _check_poses,
    ),
    "tum_poses": (
        ".txt",
        pose_io.read_tum_poses,
        _TEXT_FILES["tum_poses"],
        lambda out: (_finite(out[0]), _check_poses(out[1])),
    ),
    "auto_poses": (
        ".txt",
        lambda p: pose_io.read_poses(p).poses,
        _TEXT_FILES["kitti_poses"],
        _check_poses,
    ),
    "kitti_times": (".txt", pose_io.read_kitti_times, _TEXT_FILES["times"], _finite),
    "kitti_calib": (
        ".txt",
        read_kitti_calib,
        _TEXT_FILES["calib"],
        lambda K: (_finite(K), K.shape == (4,) or _fail()),
    ),
    "vkitti1_extrinsics": (
        ".txt",
        lambda p: read_vkitti_extrinsics(p, 1),
        _TEXT_FILES["vkitti1_extrinsics"],
        lambda t: _check_matrices(t, (4, 4)),
    ),
    "vkitti2_extrinsics": (
        ".txt",
        lambda p: read_vkitti_extrinsics(p, 2),
        _TEXT_FILES["vkitti2_extrinsics"],
        lambda t: _check_matrices(t, (4, 4)),
    ),
    "vkitti2_intrinsics": (
        ".txt",
        read_vkitti_intrinsics,
        _TEXT_FILES["vkitti2_intrinsics"],
        lambda t: _check_matrices(t, (4,)),
    ),
}


def _fail() -> None:
    raise AssertionError("a reader returned a malformed result")


# --------------------------------------------------------------------------------------------
# Corruptions
# --------------------------------------------------------------------------------------------

# Tokens that break numeric text in the ways real files break: non-finite or overflowing
# numbers, stray characters, encoding garbage, absurd lengths.
_BAD_TOKENS = st.sampled_from(
    ["nan", "inf", "-inf", "1e999", "-1e999", "", "x", "1,5", "0x10", "\x00", "\xff\xfe", "9" * 400,
     "1e308", "-0", "3.4.5", "#", "\t", "P2:", "\r"]
)  # fmt: skip


@st.composite
def corrupted(draw: st.DrawFn, valid: bytes) -> bytes:
    """Random bytes, ``valid`` cut short, ``valid`` with bytes overwritten, or (text) with a
    token replaced, a line dropped or a line duplicated."""
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
        if draw(st.booleans()):
            del lines[i]
        else:
            lines.insert(i, lines[i] + b" " + lines[i])
        return b"\n".join(lines)
    tokens = lines[i].split(b" ") or [b""]
    j = draw(st.integers(0, len(tokens) - 1))
    tokens[j] = draw(_BAD_TOKENS).encode("utf-8", "surrogateescape")
    lines[i] = b" ".join(tokens)
    return b"\n".join(lines)


def _read_corrupt(name: str, data: bytes) -> None:
    suffix, reader, _, check = READERS[name]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"corrupt_{name}{suffix}"
        path.write_bytes(data)
        try:
            out = reader(path)
        except PROJECT_ERRORS as err:
            assert path.name in str(err), f"the error does not name the file: {err}"
            return
        check(out)


@pytest.mark.parametrize("name", sorted(READERS))
def test_valid_files_read(name: str) -> None:
    """The uncorrupted files are valid: the corruptions below start from readable input."""
    suffix, reader, valid, check = READERS[name]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"valid{suffix}"
        path.write_bytes(valid)
        check(reader(path))


@pytest.mark.parametrize("name", sorted(READERS))
@FUZZ
@given(data=st.data())
def test_corrupt_files_raise_the_projects_error_naming_the_file(name: str, data) -> None:
    _read_corrupt(name, data.draw(corrupted(READERS[name][2]), label="file bytes"))


@pytest.mark.parametrize("name", ["flo", "npy_flow", "kitti_poses", "tum_poses", "kitti_calib"])
def test_missing_and_unreadable_files_raise_the_projects_error(name: str, tmp_path: Path) -> None:
    suffix, reader, _, _ = READERS[name]
    missing = tmp_path / f"missing{suffix}"
    with pytest.raises(PROJECT_ERRORS, match=missing.name):
        reader(missing)
    directory = tmp_path / f"a_directory{suffix}"
    directory.mkdir()
    with pytest.raises(PROJECT_ERRORS, match=directory.name):
        reader(directory)


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
        if kind == "values" and t.dtype.is_floating_point:
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
