"""Reading and writing the optical-flow, depth and image files of the real datasets.

Every reader returns numpy arrays in one layout, whatever the file format:

* flow: ``(H, W, 2)`` float32, ``(u, v)`` in pixels of the file's own resolution, from the frame
  the file belongs to towards the next one (``u`` along columns, ``v`` along rows);
* valid: ``(H, W)`` bool, pixels whose flow is known;
* depth: ``(H, W)`` float32 metres along the camera z axis;
* RGB images: ``(H, W, 3)`` uint8 in R, G, B order.

Formats (``docs/formats.md``):

==========================  ===============================================================
Middlebury ``.flo``         float32 magic 202021.25, int32 width, int32 height, then
                            ``H × W × 2`` float32 ``(u, v)``; values above 1e9 mean unknown
KITTI flow ``.png``         16-bit, 3 channels in file order ``u, v, valid``:
                            ``u = (R − 32768) / 64``, ``v = (G − 32768) / 64``, valid ``B > 0``
Virtual KITTI flow ``.png`` 16-bit, 3 channels; ``B == 0`` marks invalid flow (sky);
                            ``u = (2R / 65535 − 1)(W − 1)``, ``v = (2G / 65535 − 1)(H − 1)``
``.npy`` / ``.npz``         float arrays ``(2, H, W)`` or ``(H, W, 2)``; non-finite = invalid
Virtual KITTI depth         16-bit, one channel, centimetres; 65535 (655.35 m) is the far plane
==========================  ===============================================================

OpenCV decodes colour PNGs as B, G, R, so "R" above is channel 2 of what ``cv2`` returns.
Files are read through Python (``open``) and decoded with ``cv2.imdecode`` so that a missing file,
a directory, a truncated PNG or a wrong bit depth become one
:class:`~mfg_lightning.core.data_errors.DataFileError`
naming the file, never a ``None`` that fails later. Sizes are read from the header first (a PNG's
IHDR, another image's header through Pillow, a ``.npy`` header through ``numpy.lib.format``, a
``.flo``'s two integers) and checked before anything is decoded: at most :data:`MAX_PIXELS`
pixels, and the dataset's frame size where the caller gives one (``size``). A decoder's own
failure (``cv2.error``, ``MemoryError``, a zip error) is the same one-line error naming the file.
Writers exist for the tests, the flow cache and the export (:mod:`mfg_lightning.data.export`);
they write to a temporary file beside the target and ``os.replace`` it, so a reader never sees
half a file.
"""

from __future__ import annotations

import io
import os
import struct
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

from mfg_lightning.core.atomic import atomic_write_bytes
from mfg_lightning.core.data_errors import DataFileError, file_error, read_bytes

__all__ = [
    "FLO_MAGIC",
    "MAX_PIXELS",
    "VKITTI_FAR_PLANE_M",
    "atomic_write_bytes",
    "image_size",
    "quick_check",
    "read_flo",
    "read_flow",
    "read_kitti_flow_png",
    "read_npy_flow",
    "read_rgb",
    "read_vkitti_depth",
    "read_vkitti_flow_png",
    "write_flo",
    "write_kitti_flow_png",
    "write_npy_flow",
    "write_rgb",
    "write_vkitti_depth",
    "write_vkitti_flow_png",
]

FLO_MAGIC = 202021.25
#: Virtual KITTI encodes the far plane (sky) as the largest 16-bit value in centimetres.
VKITTI_FAR_PLANE_M = 655.35
_VKITTI_FAR_CODE = 65535
# Middlebury's convention for unknown flow in .flo files.
_FLO_UNKNOWN = 1e9
#: The most pixels (height × width) an image or flow file may claim: 2**25, 72 times a KITTI
#: frame (1242 × 375) and 4 times an 8K UHD one. A decoded 16-bit, 4-channel image of this size
#: takes 256 MiB, a float32 flow field 256 MiB; a header claiming more is refused before decoding.
MAX_PIXELS = 1 << 25
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# What a decoder raises on a file it cannot decode, besides returning None: OpenCV's error, an
# allocation that fails, and numpy's and zipfile's errors on a corrupt .npy or .npz.
_DECODER_ERRORS = (
    cv2.error,
    MemoryError,
    ValueError,
    OSError,
    EOFError,
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    zlib.error,
    NotImplementedError,  # a zip compression method zipfile does not have
    RuntimeError,  # an encrypted zip member
)


# --------------------------------------------------------------------------------------------
# Low-level helpers
# --------------------------------------------------------------------------------------------


def check_size(
    path: str | os.PathLike, height: int, width: int, size: tuple[int, int] | None = None
) -> None:
    """Refuse a file whose header claims an empty size, more than :data:`MAX_PIXELS` pixels, or
    (with ``size``) another size than the dataset's frames.

    Args:
        path: the file, for the message.
        height, width: what its header says, in pixels.
        size: ``(height, width)`` the dataset's frames have, or None.

    Raises:
        DataFileError: naming the file, both sizes, before anything is allocated.
    """
    if height <= 0 or width <= 0:
        raise DataFileError(f"{path}: the header claims an empty {width}×{height} image")
    if height * width > MAX_PIXELS:
        raise DataFileError(
            f"{path}: the header claims {width}×{height} pixels, more than the {MAX_PIXELS:,} "
            "a reader decodes (mfg_lightning.flow.io.MAX_PIXELS): corrupt?"
        )
    if size is not None and (height, width) != tuple(size):
        raise DataFileError(
            f"{path}: the header claims {width}×{height} pixels, but this dataset's frames are "
            f"{size[1]}×{size[0]}"
        )


def _header_size(path: str | os.PathLike, data: bytes) -> tuple[int, int]:
    """``(height, width)`` of an encoded image from its header: a PNG's IHDR chunk (8 + 8 + 13
    bytes), any other format through Pillow (which reads the header only)."""
    if data[:8] == _PNG_SIGNATURE:
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise DataFileError(f"{path}: not a readable image (a PNG without its IHDR header)")
        width, height = struct.unpack(">II", data[16:24])
        return int(height), int(width)
    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            # Pillow's own limit warns from 89 M pixels; ours (MAX_PIXELS) is lower.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data)) as image:
                width, height = image.size
    except Image.DecompressionBombError:
        raise DataFileError(
            f"{path}: the header claims more than {MAX_PIXELS:,} pixels, the most a reader "
            "decodes (mfg_lightning.flow.io.MAX_PIXELS): corrupt?"
        ) from None
    except (UnidentifiedImageError, *_DECODER_ERRORS, SyntaxError):  # SyntaxError: Pillow's
        raise DataFileError(  # word for a malformed header
            f"{path}: not a readable image (no image header: truncated or corrupt?)"
        ) from None
    return int(height), int(width)


def _decode_png(
    path: str | os.PathLike,
    *,
    flags: int = cv2.IMREAD_UNCHANGED,
    size: tuple[int, int] | None = None,
) -> np.ndarray:
    """Decode an image file; raise :class:`DataFileError` if it is missing or unreadable, or if
    its header claims a size :func:`check_size` refuses (checked before decoding)."""
    data = read_bytes(path)
    if not data:
        raise DataFileError(f"{path}: empty file")
    check_size(path, *_header_size(path, data), size)
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except (cv2.error, MemoryError) as err:
        reason = " ".join(str(err).split()) or type(err).__name__
        raise DataFileError(f"{path}: not a readable image ({reason[:200]})") from None
    if image is None:
        raise DataFileError(f"{path}: not a readable image (truncated or corrupt?)")
    return image


def _decode_png16(
    path: str | os.PathLike, channels: int, size: tuple[int, int] | None = None
) -> np.ndarray:
    """A 16-bit PNG with ``channels`` channels, as OpenCV returns it (BGR order for 3)."""
    image = _decode_png(path, size=size)
    if image.dtype != np.uint16:
        raise DataFileError(f"{path}: expected a 16-bit PNG, got {image.dtype} ({image.shape})")
    got = 1 if image.ndim == 2 else image.shape[2]
    if got != channels:
        raise DataFileError(f"{path}: expected {channels} channel(s), got {got}")
    return image


def _encode_png(path: str | os.PathLike, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise DataFileError(f"{path}: PNG encoding failed for {image.dtype} {image.shape}")
    atomic_write_bytes(path, buf.tobytes())


def _check_flow_array(flow: np.ndarray, what: str) -> np.ndarray:
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"{what}: flow must be (H, W, 2), got {flow.shape}")
    return flow


def _valid_or_finite(flow: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    finite = np.isfinite(flow).all(axis=2)
    return finite if valid is None else (np.asarray(valid, bool) & finite)


# --------------------------------------------------------------------------------------------
# Middlebury .flo
# --------------------------------------------------------------------------------------------


def read_flo(
    path: str | os.PathLike, size: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Read a Middlebury ``.flo`` file.

    Args:
        path: the file.
        size: ``(height, width)`` the header must claim, or None (any, up to
            :data:`MAX_PIXELS`).

    Returns:
        ``(flow, valid)``: ``(H, W, 2)`` float32 pixels and ``(H, W)`` bool; pixels with a
        non-finite component or a magnitude above 1e9 (Middlebury's "unknown") are invalid and
        their flow is set to 0.
    """
    data = read_bytes(path)
    if len(data) < 12:
        raise DataFileError(f"{path}: .flo file too short for its header ({len(data)} bytes)")
    magic = np.frombuffer(data, "<f4", count=1)[0]
    if magic != np.float32(FLO_MAGIC):
        raise DataFileError(f"{path}: wrong .flo magic number {magic!r} (expected {FLO_MAGIC})")
    width, height = (int(x) for x in np.frombuffer(data, "<i4", count=2, offset=4))
    check_size(path, height, width, size)
    expected = 12 + 8 * width * height
    if len(data) != expected:
        raise DataFileError(
            f"{path}: .flo file has {len(data)} bytes, expected {expected} for {width}×{height}"
        )
    flow = np.frombuffer(data, "<f4", offset=12).reshape(height, width, 2).astype(np.float32)
    valid = np.isfinite(flow).all(axis=2) & (np.abs(flow) < _FLO_UNKNOWN).all(axis=2)
    flow[~valid] = 0.0
    return flow, valid


def write_flo(path: str | os.PathLike, flow: np.ndarray, valid: np.ndarray | None = None) -> None:
    """Write ``(H, W, 2)`` flow as ``.flo``; invalid pixels are stored as the unknown value."""
    flow = _check_flow_array(flow, str(path)).astype("<f4", copy=True)
    if valid is not None:
        flow[~np.asarray(valid, bool)] = np.float32(2 * _FLO_UNKNOWN)
    height, width = flow.shape[:2]
    header = np.array([FLO_MAGIC], "<f4").tobytes() + np.array([width, height], "<i4").tobytes()
    atomic_write_bytes(path, header + flow.tobytes())


# --------------------------------------------------------------------------------------------
# KITTI flow PNG
# --------------------------------------------------------------------------------------------


def read_kitti_flow_png(
    path: str | os.PathLike, size: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI flow PNG (file channels u, v, valid; OpenCV returns them as B=valid, G=v, R=u).

    ``size``: ``(height, width)`` the header must claim, or None (any, up to :data:`MAX_PIXELS`).

    Returns:
        ``(flow, valid)``: ``(H, W, 2)`` float32 pixels (0 where invalid), ``(H, W)`` bool.
    """
    bgr = _decode_png16(path, 3, size)
    valid = bgr[..., 0] > 0
    flow = (bgr[..., [2, 1]].astype(np.float32) - 32768.0) / 64.0
    flow[~valid] = 0.0
    return flow, valid


def write_kitti_flow_png(
    path: str | os.PathLike, flow: np.ndarray, valid: np.ndarray | None = None
) -> None:
    """Write ``(H, W, 2)`` flow as a KITTI flow PNG (1/64 px steps, range ±512 px, clipped)."""
    flow = _check_flow_array(flow, str(path))
    valid = _valid_or_finite(flow, valid)
    codes = np.clip(np.round(np.nan_to_num(flow) * 64.0 + 32768.0), 0, 65535).astype(np.uint16)
    bgr = np.stack([valid.astype(np.uint16), codes[..., 1], codes[..., 0]], axis=2)
    bgr[~valid, 1:] = 0
    _encode_png(path, bgr)


# --------------------------------------------------------------------------------------------
# Virtual KITTI flow PNG and depth PNG
# --------------------------------------------------------------------------------------------


def read_vkitti_flow_png(
    path: str | os.PathLike, size: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Read a Virtual KITTI (1.3.1 or 2.0.3) forward-flow PNG.

    ``size``: ``(height, width)`` the header must claim, or None (any, up to :data:`MAX_PIXELS`).

    Returns:
        ``(flow, valid)``: ``(H, W, 2)`` float32 pixels (0 where invalid), ``(H, W)`` bool
        (``B == 0`` is invalid: the sky and pixels leaving the image).
    """
    bgr = _decode_png16(path, 3, size)
    height, width = bgr.shape[:2]
    valid = bgr[..., 0] > 0
    scale = np.array([width - 1, height - 1], np.float32)
    flow = (2.0 / 65535.0 * bgr[..., [2, 1]].astype(np.float32) - 1.0) * scale
    flow[~valid] = 0.0
    return flow, valid


def write_vkitti_flow_png(
    path: str | os.PathLike, flow: np.ndarray, valid: np.ndarray | None = None
) -> None:
    """Write ``(H, W, 2)`` flow in the Virtual KITTI encoding (inverse of the reader)."""
    flow = _check_flow_array(flow, str(path))
    height, width = flow.shape[:2]
    valid = _valid_or_finite(flow, valid)
    scale = np.array([width - 1, height - 1], np.float64)
    codes = (np.nan_to_num(flow) / scale + 1.0) * (65535.0 / 2.0)
    codes = np.clip(np.round(codes), 0, 65535).astype(np.uint16)
    bgr = np.stack([valid.astype(np.uint16) * 65535, codes[..., 1], codes[..., 0]], axis=2)
    bgr[~valid, 1:] = 0
    _encode_png(path, bgr)


def read_vkitti_depth(
    path: str | os.PathLike, size: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Read a Virtual KITTI depth PNG (16-bit centimetres along z).

    ``size``: ``(height, width)`` the header must claim, or None (any, up to :data:`MAX_PIXELS`).

    Returns:
        ``(depth, far)``: ``(H, W)`` float32 metres (the far plane reads as 655.35 m, as stored)
        and ``(H, W)`` bool marking far-plane pixels (sky), which have no usable depth.
    """
    raw = _decode_png16(path, 1, size)
    far = raw == _VKITTI_FAR_CODE
    return raw.astype(np.float32) / 100.0, far


def write_vkitti_depth(path: str | os.PathLike, depth_m: np.ndarray) -> None:
    """Write ``(H, W)`` depth in metres as a 16-bit centimetre PNG; ≥ 655.35 m or non-finite
    becomes the far plane."""
    depth_m = np.asarray(depth_m, np.float64)
    if depth_m.ndim != 2:
        raise ValueError(f"{path}: depth must be (H, W), got {depth_m.shape}")
    cm = np.where(np.isfinite(depth_m), np.round(depth_m * 100.0), _VKITTI_FAR_CODE)
    _encode_png(path, np.clip(cm, 0, _VKITTI_FAR_CODE).astype(np.uint16))


# --------------------------------------------------------------------------------------------
# numpy flow
# --------------------------------------------------------------------------------------------


def _npy_header(
    path: Path, f: BinaryIO, stored: int, size: tuple[int, int] | None
) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of the ``.npy`` stream ``f`` (at its start) from its header, checked as
    flow before the array is read: a float dtype, ``(2, H, W)`` or ``(H, W, 2)`` with at most
    :data:`MAX_PIXELS` pixels (and ``size``, if given), and as many bytes after the header as the
    shape needs.

    Args:
        path: the file, for messages.
        f: the stream, positioned at the magic string.
        stored: bytes in the stream (the file's size, an archive member's uncompressed size).
        size: ``(height, width)`` the flow must have, or None.
    """
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(f)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(f)
    else:  # 3.0 only adds UTF-8 field names: a structured dtype, never flow
        raise DataFileError(f"{path}: .npy format version {version} is not one flow is saved in")
    if not np.issubdtype(dtype, np.floating):
        raise DataFileError(f"{path}: flow must be a float array, got dtype {dtype}")
    if len(shape) == 3 and shape[2] == 2:
        check_size(path, shape[0], shape[1], size)
    elif len(shape) == 3 and shape[0] == 2:
        check_size(path, shape[1], shape[2], size)
    else:
        raise DataFileError(f"{path}: flow must be (2, H, W) or (H, W, 2), got {shape}")
    needed = f.tell() + int(np.prod(shape)) * dtype.itemsize
    if stored < needed:
        raise DataFileError(
            f"{path}: truncated: {stored} bytes, its header's {shape} {dtype} needs {needed}"
        )
    return shape, dtype


def read_npy_flow(
    path: str | os.PathLike, size: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Read flow saved with numpy: ``.npy``, or ``.npz`` holding one array (or one named
    ``flow``), shaped ``(2, H, W)`` or ``(H, W, 2)``.

    The header is read first (``numpy.lib.format``) and its dtype, shape and size checked
    before the array is (:func:`check_size`).

    Args:
        path: the file.
        size: ``(height, width)`` the flow must have, or None (any, up to :data:`MAX_PIXELS`).

    Returns:
        ``(flow, valid)``: ``(H, W, 2)`` float32 (0 where non-finite) and ``(H, W)`` bool.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            if f.read(4) in (b"PK\x03\x04", b"PK\x05\x06"):  # a zip archive, as numpy tells
                array = _read_npz_member(path, size)
            else:
                f.seek(0)
                _npy_header(path, f, os.fstat(f.fileno()).st_size, size)
                f.seek(0)
                array = np.lib.format.read_array(f, allow_pickle=False)
    except DataFileError:
        raise
    except (FileNotFoundError, IsADirectoryError, PermissionError) as err:
        raise DataFileError(file_error(path, err)) from None
    except _DECODER_ERRORS as err:
        reason = " ".join(str(err).split()) or type(err).__name__
        raise DataFileError(f"{path}: not a readable numpy file ({reason[:200]})") from None
    flow = array if array.shape[2] == 2 else np.moveaxis(array, 0, 2)
    flow = np.ascontiguousarray(flow, dtype=np.float32)
    valid = np.isfinite(flow).all(axis=2)
    flow[~valid] = 0.0
    return flow, valid


def _read_npz_member(path: Path, size: tuple[int, int] | None) -> np.ndarray:
    """The flow array of an ``.npz``: its one array, or the one named ``flow``, header first."""
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
        keys = [n.removesuffix(".npy") for n in names]
        if "flow" in keys:
            name = names[keys.index("flow")]
        elif len(names) == 1:
            name = names[0]
        else:
            raise DataFileError(
                f"{path}: .npz holds {keys}; expected one array or one named 'flow'"
            )
        if not name.endswith(".npy"):
            raise DataFileError(f"{path}: .npz member {name!r} is not a numpy array (.npy)")
        stored = archive.getinfo(name).file_size
        with archive.open(name) as member:
            _npy_header(path, member, stored, size)
        with archive.open(name) as member:
            return np.lib.format.read_array(member, allow_pickle=False)


def write_npy_flow(
    path: str | os.PathLike, flow: np.ndarray, valid: np.ndarray | None = None
) -> None:
    """Write ``(H, W, 2)`` flow as a ``.npy`` float32 array ``(H, W, 2)``; invalid → NaN."""
    flow = _check_flow_array(flow, str(path)).astype(np.float32, copy=True)
    if valid is not None:
        flow[~np.asarray(valid, bool)] = np.nan
    buf = io.BytesIO()
    np.save(buf, flow, allow_pickle=False)
    atomic_write_bytes(path, buf.getvalue())


# --------------------------------------------------------------------------------------------
# Dispatch and images
# --------------------------------------------------------------------------------------------


def read_flow(
    path: str | os.PathLike, png_format: str = "kitti", size: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Read any supported flow file, choosing the reader by extension.

    ``.png`` is ambiguous (KITTI and Virtual KITTI encode flow differently): ``png_format``
    says which, ``"kitti"`` (default, the format of user-supplied flow) or ``"vkitti"``.
    ``size``: ``(height, width)`` the file must hold, or None (any, up to :data:`MAX_PIXELS`).

    Returns:
        ``(flow, valid)``: ``(H, W, 2)`` float32 pixels, ``(H, W)`` bool.
    """
    suffix = Path(path).suffix.lower()
    if suffix == ".flo":
        return read_flo(path, size)
    if suffix in (".npy", ".npz"):
        return read_npy_flow(path, size)
    if suffix == ".png":
        if png_format == "kitti":
            return read_kitti_flow_png(path, size)
        if png_format == "vkitti":
            return read_vkitti_flow_png(path, size)
        raise ValueError(f"png_format must be 'kitti' or 'vkitti', got {png_format!r}")
    raise DataFileError(f"{path}: unknown flow file extension {suffix!r} (.flo, .png, .npy, .npz)")


def read_rgb(path: str | os.PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read an 8-bit colour (or grey) image as ``(H, W, 3)`` uint8 RGB.

    ``size``: ``(height, width)`` the header must claim, or None (any, up to :data:`MAX_PIXELS`).
    """
    image = _decode_png(path, size=size)
    if image.dtype != np.uint8:
        raise DataFileError(f"{path}: expected an 8-bit image, got {image.dtype}")
    if image.ndim == 2:
        return np.repeat(image[..., None], 3, axis=2)
    if image.shape[2] == 4:
        image = image[..., :3]
    if image.shape[2] != 3:
        raise DataFileError(f"{path}: expected 1, 3 or 4 channels, got {image.shape[2]}")
    return np.ascontiguousarray(image[..., ::-1])


def write_rgb(path: str | os.PathLike, rgb: np.ndarray, jpeg_quality: int = 95) -> None:
    """Write ``(H, W, 3)`` uint8 RGB as an 8-bit colour image, the format from the suffix:
    ``.png`` (lossless; KITTI, Virtual KITTI 1.3.1) or ``.jpg``/``.jpeg`` (Virtual KITTI 2.0.3;
    lossy, at ``jpeg_quality``). The inverse of :func:`read_rgb` (exactly, for PNG)."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"{path}: RGB must be (H, W, 3) uint8, got {rgb.dtype} {rgb.shape}")
    suffix = Path(path).suffix.lower()
    if suffix not in (".png", ".jpg", ".jpeg"):
        raise ValueError(f"{path}: write_rgb writes .png or .jpg, not {suffix or 'no suffix'}")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if suffix != ".png" else []
    ok, buf = cv2.imencode(suffix, np.ascontiguousarray(rgb[..., ::-1]), params)
    if not ok:
        raise DataFileError(f"{path}: image encoding failed for {rgb.shape}")
    atomic_write_bytes(path, buf.tobytes())


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """``(height, width)`` of an image file, raising :class:`DataFileError` if unreadable.

    Read from the header without decoding the pixels: a PNG's IHDR (its first 24 bytes), other
    formats (Virtual KITTI 2's JPEG) through Pillow. A size :func:`check_size` refuses (empty,
    more than :data:`MAX_PIXELS`) is an error here too.
    """
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError as err:
        raise DataFileError(file_error(path, err)) from None
    if len(head) == 24 and head[:8] == _PNG_SIGNATURE and head[12:16] == b"IHDR":
        width, height = struct.unpack(">II", head[16:24])
        hw = int(height), int(width)
    else:
        hw = _header_size(path, read_bytes(path))
    check_size(path, *hw)
    return hw


def quick_check(path: str | os.PathLike) -> str | None:
    """A cheap integrity check of an image file, without decoding it.

    Reads the first 24 and the last 32 bytes: the file must exist, be a PNG or JPEG by its
    signature, and end with the format's end marker (PNG's ``IEND`` chunk, JPEG's ``FFD9``), which
    catches truncated downloads. Other files (``.flo``, ``.npy``, text) only have to exist and be
    non-empty.

    Returns:
        None if the file looks whole, else a one-line description of the problem.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size == 0:
            return f"{path}: empty file"
        with open(path, "rb") as f:
            head = f.read(24)
            f.seek(max(0, size - 32))
            tail = f.read()
    except FileNotFoundError:
        return f"{path}: file not found"
    except OSError as err:
        return f"{path}: cannot read ({err.strerror or err})"
    if head[:8] == b"\x89PNG\r\n\x1a\n":
        return None if tail.endswith(b"IEND\xaeB`\x82") else f"{path}: truncated PNG (no IEND)"
    if head[:2] == b"\xff\xd8":
        return None if b"\xff\xd9" in tail else f"{path}: truncated JPEG (no end marker)"
    if path.suffix.lower() in (".png", ".jpg", ".jpeg"):
        return f"{path}: not a {path.suffix[1:].upper()} file (bad signature)"
    return None
