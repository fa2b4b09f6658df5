"""Property-based tests (hypothesis) of every reader at once: each either refuses its input
with the project's one-line data error naming the file, or returns something that means what the
format says (``tests/fuzz_readers.py`` says what a result must mean).

The inputs here: each format's valid file, read back as written; the valid files garbled byte by
byte or token by token; missing files and directories. What Hypothesis found in the readers
before they checked meaning and sizes is kept in ``tests/data/fuzz_regressions/`` and read on
every run. Header fields drawn by strategies are in ``test_fuzz_headers.py`` (images, flow) and
``test_fuzz_poses.py`` (poses, cameras); checkpoints and batches have files of their own.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzz_readers import FUZZ, PROJECT_ERRORS, READERS, VALID_CONTENTS, _read
from mfg_lightning.data.kitti import read_kitti_calib
from mfg_lightning.data.vkitti_files import read_vkitti_extrinsics, read_vkitti_intrinsics
from mfg_lightning.flow import io as flow_io
from mfg_lightning.run.checkpoints import CheckpointError, load_checkpoint

REGRESSIONS = Path(__file__).parent / "data" / "fuzz_regressions"


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
