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
a truncated PNG or a wrong bit depth become one
:class:`~mfg_lightning.core.data_errors.DataFileError`
naming the file, never a ``None`` that fails later. Writers exist for the tests, the flow cache
and the export (:mod:`mfg_lightning.data.export`); they write to a temporary file beside the
target and ``os.replace`` it, so a reader never sees half a file.
"""

from __future__ import annotations

import io
import os
import struct
import zipfile
import zlib
from pathlib import Path

import cv2
import numpy as np

from mfg_lightning.core.atomic import atomic_write_bytes
from mfg_lightning.core.data_errors import DataFileError, read_bytes

__all__ = [
    "FLO_MAGIC",
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


# --------------------------------------------------------------------------------------------
# Low-level helpers
# --------------------------------------------------------------------------------------------


def _decode_png(path: str | os.PathLike, *, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    """Decode an image file; raise :class:`DataFileError` if it is missing or unreadable."""
    data = read_bytes(path)
    if not data:
        raise DataFileError(f"{path}: empty file")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if image is None:
        raise DataFileError(f"{path}: not a readable image (truncated or corrupt?)")
    return image


def _decode_png16(path: str | os.PathLike, channels: int) -> np.ndarray:
    """A 16-bit PNG with ``channels`` channels, as OpenCV returns it (BGR order for 3)."""
    image = _decode_png(path)
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


def read_flo(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a Middlebury ``.flo`` file.

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
    if width <= 0 or height <= 0 or width * height > 1 << 28:
        raise DataFileError(f"{path}: implausible .flo size {width}×{height}")
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


def read_kitti_flow_png(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI flow PNG (file channels u, v, valid; OpenCV returns them as B=valid, G=v, R=u).

    Returns:
        ``(flow, valid)``: ``(H, W, 2)`` float32 pixels (0 where invalid), ``(H, W)`` bool.
    """
    bgr = _decode_png16(path, 3)
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


def read_vkitti_flow_png(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a Virtual KITTI (1.3.1 or 2.0.3) forward-flow PNG.

    Returns:
        ``(flow, valid)``: ``(H, W, 2)`` float32 pixels (0 where invalid), ``(H, W)`` bool
        (``B == 0`` is invalid: the sky and pixels leaving the image).
    """
    bgr = _decode_png16(path, 3)
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


def read_vkitti_depth(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a Virtual KITTI depth PNG (16-bit centimetres along z).

    Returns:
        ``(depth, far)``: ``(H, W)`` float32 metres (the far plane reads as 655.35 m, as stored)
        and ``(H, W)`` bool marking far-plane pixels (sky), which have no usable depth.
    """
    raw = _decode_png16(path, 1)
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


def read_npy_flow(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read flow saved with numpy: ``.npy``, or ``.npz`` holding one array (or one named
    ``flow``), shaped ``(2, H, W)`` or ``(H, W, 2)``.

    Returns:
        ``(flow, valid)``: ``(H, W, 2)`` float32 (0 where non-finite) and ``(H, W)`` bool.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFileError(f"{path}: file not found")
    try:
        loaded = np.load(path, allow_pickle=False)
        if isinstance(loaded, np.lib.npyio.NpzFile):
            with loaded:
                keys = list(loaded.keys())
                if "flow" in keys:
                    array = loaded["flow"]
                elif len(keys) == 1:
                    array = loaded[keys[0]]
                else:
                    raise DataFileError(
                        f"{path}: .npz holds {keys}; expected one array or one named 'flow'"
                    )
        else:
            array = loaded
    except DataFileError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as err:
        # zipfile/zlib: a corrupt or truncated .npz archive
        raise DataFileError(f"{path}: not a readable numpy file ({err})") from None
    if not np.issubdtype(array.dtype, np.floating):
        raise DataFileError(f"{path}: flow must be a float array, got dtype {array.dtype}")
    if array.ndim == 3 and array.shape[2] == 2:
        flow = array
    elif array.ndim == 3 and array.shape[0] == 2:
        flow = np.moveaxis(array, 0, 2)
    else:
        raise DataFileError(f"{path}: flow must be (2, H, W) or (H, W, 2), got {array.shape}")
    flow = np.ascontiguousarray(flow, dtype=np.float32)
    valid = np.isfinite(flow).all(axis=2)
    flow[~valid] = 0.0
    return flow, valid


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


def read_flow(path: str | os.PathLike, png_format: str = "kitti") -> tuple[np.ndarray, np.ndarray]:
    """Read any supported flow file, choosing the reader by extension.

    ``.png`` is ambiguous (KITTI and Virtual KITTI encode flow differently): ``png_format``
    says which, ``"kitti"`` (default, the format of user-supplied flow) or ``"vkitti"``.

    Returns:
        ``(flow, valid)``: ``(H, W, 2)`` float32 pixels, ``(H, W)`` bool.
    """
    suffix = Path(path).suffix.lower()
    if suffix == ".flo":
        return read_flo(path)
    if suffix in (".npy", ".npz"):
        return read_npy_flow(path)
    if suffix == ".png":
        if png_format == "kitti":
            return read_kitti_flow_png(path)
        if png_format == "vkitti":
            return read_vkitti_flow_png(path)
        raise ValueError(f"png_format must be 'kitti' or 'vkitti', got {png_format!r}")
    raise DataFileError(f"{path}: unknown flow file extension {suffix!r} (.flo, .png, .npy, .npz)")


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """Read an 8-bit colour (or grey) image as ``(H, W, 3)`` uint8 RGB."""
    image = _decode_png(path)
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

    PNG sizes are read from the IHDR header (24 bytes) without decoding the pixels; other
    formats (Virtual KITTI 2's JPEG) are decoded.
    """
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except FileNotFoundError:
        raise DataFileError(f"{path}: file not found") from None
    except OSError as err:
        raise DataFileError(f"{path}: cannot read ({err.strerror or err})") from None
    if len(head) == 24 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        width, height = struct.unpack(">II", head[16:24])
        return int(height), int(width)
    image = _decode_png(path)
    return int(image.shape[0]), int(image.shape[1])


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
