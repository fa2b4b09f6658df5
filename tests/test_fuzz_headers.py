"""Property-based tests (hypothesis) of the image and flow readers on header fields drawn by
the strategies: PNG and JPEG sizes, ``.npy`` shapes and dtypes, ``.flo`` widths and heights.
Each reader refuses the file with the project's one-line data error naming it, or returns an
image or flow field of the size the header claims, within the stated bound."""

from __future__ import annotations

import io
import struct
import zipfile

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fake_datasets import npy_header_only, png_header_only
from fuzz_readers import HEADERS, _read
from mfg_lightning.flow import io as flow_io

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
