"""Flow, depth and image files decode to the values written; resizing keeps its promises."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from fake_datasets import npy_header_only, png_header_only
from mfg_lightning.core import geometry
from mfg_lightning.core.data_errors import DataFileError
from mfg_lightning.data import transforms
from mfg_lightning.flow import io as flow_io


def _random_flow(h: int = 12, w: int = 17, scale: float = 20.0, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).uniform(-1, 1, (h, w, 2)) * scale).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------------


def test_flo_round_trip_and_unknown_pixels(tmp_path: Path) -> None:
    flow = _random_flow()
    valid = np.ones(flow.shape[:2], bool)
    valid[3, 4] = valid[0, 0] = False
    flow_io.write_flo(tmp_path / "a.flo", flow, valid)
    got, got_valid = flow_io.read_flo(tmp_path / "a.flo")
    np.testing.assert_array_equal(got_valid, valid)
    np.testing.assert_array_equal(got[valid], flow[valid])  # float32 stored exactly
    assert (got[~valid] == 0).all()
    # The header: magic, then width, then height.
    raw = (tmp_path / "a.flo").read_bytes()
    assert np.frombuffer(raw[:4], "<f4")[0] == np.float32(202021.25)
    assert tuple(np.frombuffer(raw[4:12], "<i4")) == (17, 12)


def test_kitti_png_encoding_matches_the_published_formula(tmp_path: Path) -> None:
    flow = np.round(_random_flow() * 64) / 64  # representable exactly
    valid = np.ones(flow.shape[:2], bool)
    valid[5, :3] = False
    path = tmp_path / "k.png"
    flow_io.write_kitti_flow_png(path, flow, valid)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # B, G, R = valid, v, u
    assert raw.dtype == np.uint16 and raw.shape == (12, 17, 3)
    np.testing.assert_array_equal(
        (raw[..., 2][valid].astype(float) - 32768) / 64, flow[..., 0][valid]
    )
    np.testing.assert_array_equal(
        (raw[..., 1][valid].astype(float) - 32768) / 64, flow[..., 1][valid]
    )
    got, got_valid = flow_io.read_kitti_flow_png(path)
    np.testing.assert_array_equal(got_valid, valid)
    np.testing.assert_array_equal(got[valid], flow[valid])
    assert (got[~valid] == 0).all()


def test_vkitti_png_encoding_matches_the_published_formula(tmp_path: Path) -> None:
    h, w = 20, 31
    flow = _random_flow(h, w, scale=15.0)
    valid = np.ones((h, w), bool)
    valid[:4] = False  # sky
    path = tmp_path / "v.png"
    flow_io.write_vkitti_flow_png(path, flow, valid)
    bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)
    assert (bgr[..., 0][~valid] == 0).all() and (bgr[..., 0][valid] > 0).all()
    expected_u = (2 * bgr[..., 2] / 65535 - 1) * (w - 1)
    expected_v = (2 * bgr[..., 1] / 65535 - 1) * (h - 1)
    got, got_valid = flow_io.read_vkitti_flow_png(path)
    np.testing.assert_array_equal(got_valid, valid)
    np.testing.assert_allclose(got[..., 0][valid], expected_u[valid], atol=1e-4)
    np.testing.assert_allclose(got[..., 1][valid], expected_v[valid], atol=1e-4)
    # Quantisation: half a 16-bit step of (W − 1)·2/65535 pixels.
    np.testing.assert_allclose(got[valid], flow[valid], atol=(w - 1) / 65535 + 1e-5)
    assert (got[~valid] == 0).all()


def test_vkitti_depth_far_plane(tmp_path: Path) -> None:
    depth = np.array([[1.23, 655.35, 80.0], [np.inf, 0.5, 700.0]])
    flow_io.write_vkitti_depth(tmp_path / "d.png", depth)
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw[0, 0] == 123 and raw[0, 1] == 65535
    got, far = flow_io.read_vkitti_depth(tmp_path / "d.png")
    np.testing.assert_allclose(got, [[1.23, 655.35, 80.0], [655.35, 0.5, 655.35]], atol=1e-5)
    np.testing.assert_array_equal(far, [[False, True, False], [True, False, True]])


@pytest.mark.parametrize("layout", ["chw", "hwc", "npz"])
def test_numpy_flow_layouts(tmp_path: Path, layout: str) -> None:
    flow = _random_flow()
    flow[2, 2, 0] = np.nan
    if layout == "chw":
        np.save(tmp_path / "f.npy", np.moveaxis(flow, 2, 0))
        path = tmp_path / "f.npy"
    elif layout == "hwc":
        np.save(tmp_path / "f.npy", flow)
        path = tmp_path / "f.npy"
    else:
        np.savez(tmp_path / "f.npz", flow=flow.astype(np.float64))
        path = tmp_path / "f.npz"
    got, valid = flow_io.read_flow(path)
    assert got.shape == (12, 17, 2) and got.dtype == np.float32
    assert not valid[2, 2] and valid.sum() == valid.size - 1
    assert got[2, 2, 0] == 0
    np.testing.assert_allclose(got[valid], flow[valid], rtol=1e-6)


def test_read_flow_dispatches_by_extension(tmp_path: Path) -> None:
    flow = np.round(_random_flow() * 64) / 64
    flow_io.write_flo(tmp_path / "a.flo", flow)
    flow_io.write_kitti_flow_png(tmp_path / "a.png", flow)
    flow_io.write_npy_flow(tmp_path / "a.npy", flow)
    for name in ("a.flo", "a.png", "a.npy"):
        got, valid = flow_io.read_flow(tmp_path / name)
        assert valid.all(), name
        np.testing.assert_allclose(got, flow, atol=1e-6, err_msg=name)
    small = flow / 4  # Virtual KITTI's encoding spans ±(W − 1) = ±16 px here
    flow_io.write_vkitti_flow_png(tmp_path / "v.png", small)
    got, _ = flow_io.read_flow(tmp_path / "v.png", png_format="vkitti")
    np.testing.assert_allclose(got, small, atol=16 / 65535 + 1e-5)


def test_rgb_is_returned_in_rgb_order(tmp_path: Path) -> None:
    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[..., 2] = 200  # red in OpenCV's BGR
    cv2.imwrite(str(tmp_path / "r.png"), bgr)
    rgb = flow_io.read_rgb(tmp_path / "r.png")
    assert rgb.shape == (4, 5, 3) and (rgb[..., 0] == 200).all() and (rgb[..., 2] == 0).all()
    assert flow_io.image_size(tmp_path / "r.png") == (4, 5)


def test_rgb_writer_round_trips_png_exactly_and_jpeg_closely(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    rgb = cv2.GaussianBlur(rng.integers(0, 256, (24, 40, 3), dtype=np.uint8), (0, 0), 3.0)
    flow_io.write_rgb(tmp_path / "a.png", rgb)
    np.testing.assert_array_equal(flow_io.read_rgb(tmp_path / "a.png"), rgb)
    flow_io.write_rgb(tmp_path / "a.jpg", rgb)  # Virtual KITTI 2.0.3's RGB frames are JPEG
    assert (tmp_path / "a.jpg").read_bytes()[:2] == b"\xff\xd8"
    err = np.abs(flow_io.read_rgb(tmp_path / "a.jpg").astype(int) - rgb.astype(int))
    assert err.mean() < 3.0
    with pytest.raises(ValueError, match=r"\.tif"):
        flow_io.write_rgb(tmp_path / "a.tif", rgb)
    with pytest.raises(ValueError, match="uint8"):
        flow_io.write_rgb(tmp_path / "b.png", rgb.astype(np.float32))


# --------------------------------------------------------------------------------------------
# Bad files
# --------------------------------------------------------------------------------------------


def test_bad_files_raise_data_file_error_naming_the_file(tmp_path: Path) -> None:
    flow = _random_flow()
    # missing
    with pytest.raises(DataFileError, match="nope.png: file not found"):
        flow_io.read_kitti_flow_png(tmp_path / "nope.png")
    # truncated PNG
    flow_io.write_kitti_flow_png(tmp_path / "t.png", flow)
    data = (tmp_path / "t.png").read_bytes()
    (tmp_path / "t.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(DataFileError, match=r"t\.png: not a readable image"):
        flow_io.read_kitti_flow_png(tmp_path / "t.png")
    assert "truncated PNG" in flow_io.quick_check(tmp_path / "t.png")
    # wrong bit depth: an 8-bit PNG where 16-bit flow is expected
    cv2.imwrite(str(tmp_path / "8bit.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(DataFileError, match=r"8bit\.png: expected a 16-bit PNG"):
        flow_io.read_vkitti_flow_png(tmp_path / "8bit.png")
    assert flow_io.quick_check(tmp_path / "8bit.png") is None  # whole, just the wrong kind
    # wrong channel count: a depth-like 1-channel 16-bit PNG read as flow
    flow_io.write_vkitti_depth(tmp_path / "d.png", np.ones((4, 4)))
    with pytest.raises(DataFileError, match="expected 3 channel"):
        flow_io.read_vkitti_flow_png(tmp_path / "d.png")
    # wrong .flo magic, truncated .flo
    flow_io.write_flo(tmp_path / "a.flo", flow)
    raw = bytearray((tmp_path / "a.flo").read_bytes())
    (tmp_path / "short.flo").write_bytes(bytes(raw[:-8]))
    with pytest.raises(DataFileError, match=r"short\.flo: .flo file has"):
        flow_io.read_flo(tmp_path / "short.flo")
    raw[:4] = np.array([1.0], "<f4").tobytes()
    (tmp_path / "magic.flo").write_bytes(bytes(raw))
    with pytest.raises(DataFileError, match=r"magic\.flo: wrong .flo magic"):
        flow_io.read_flo(tmp_path / "magic.flo")
    # wrong shape / dtype in numpy files
    np.save(tmp_path / "shape.npy", np.zeros((3, 4, 5), np.float32))
    with pytest.raises(DataFileError, match=r"shape\.npy: flow must be \(2, H, W\) or \(H, W, 2\)"):
        flow_io.read_flow(tmp_path / "shape.npy")
    np.save(tmp_path / "int.npy", np.zeros((4, 5, 2), np.int32))
    with pytest.raises(DataFileError, match=r"int\.npy: flow must be a float array"):
        flow_io.read_flow(tmp_path / "int.npy")
    with pytest.raises(DataFileError, match="unknown flow file extension"):
        flow_io.read_flow(tmp_path / "flow.txt")


# --------------------------------------------------------------------------------------------
# Resizing
# --------------------------------------------------------------------------------------------


def test_resize_flow_scales_values_and_never_mixes_invalid_pixels() -> None:
    h, w = 40, 60
    flow = np.zeros((h, w, 2), np.float32)
    flow[..., 0], flow[..., 1] = 6.0, -3.0
    valid = np.ones((h, w), bool)
    flow[:10] = 1e6  # garbage under invalid pixels must not leak
    valid[:10] = False
    valid[20:30:2, ::2] = False  # scattered holes: a quarter of these rows
    out, out_valid = transforms.resize_flow(flow, valid, 10, 20)
    # values scaled by the width and height ratios, on every valid output pixel
    np.testing.assert_allclose(out[out_valid][:, 0], 6.0 * 20 / 60, rtol=1e-5)
    np.testing.assert_allclose(out[out_valid][:, 1], -3.0 * 10 / 40, rtol=1e-5)
    assert not out_valid[:2].any() and out_valid[3:].all()  # rows 0–9 → output rows 0–2.5
    assert (out[~out_valid] == 0).all()


def test_resize_depth_is_the_harmonic_mean_and_keeps_unknown_zero() -> None:
    depth = np.array([[10.0, 30.0], [0.0, 0.0]], np.float32)
    out = transforms.resize_depth(np.kron(depth, np.ones((4, 4), np.float32)), 2, 1)
    # top half: 1 / mean(1/10, 1/30) = 15 m; bottom half: unknown stays 0
    np.testing.assert_allclose(out[:, 0], [15.0, 0.0], rtol=1e-5)


def test_resized_depth_gives_the_area_mean_of_the_rigid_flow() -> None:
    """Why inverse depth: the motion field is linear in ρ, so area-averaging ρ and the flow
    commute (up to the variation of A within a pixel)."""
    rng = np.random.default_rng(1)
    depth = np.kron(rng.uniform(3, 60, (6, 8)), np.ones((8, 8)))  # sharp depth edges
    K = torch.tensor([[40.0, 40.0, 31.5, 23.5]], dtype=torch.float64)
    t = torch.tensor([[0.0, 0.0, 0.5]], dtype=torch.float64)
    w = torch.zeros(1, 3, dtype=torch.float64)
    field = geometry.motion_field(t, w, torch.from_numpy(1 / depth)[None], K)[0]
    fine = field.permute(1, 2, 0).numpy()
    coarse, _ = transforms.resize_flow(fine, np.ones(depth.shape, bool), 12, 16)
    K_lr = geometry.scale_intrinsics(K, 16 / 64, 12 / 48)
    rho = 1 / transforms.resize_depth(depth, 12, 16)
    from_depth = geometry.motion_field(t, w, torch.from_numpy(rho)[None], K_lr)[0]
    err = np.abs(from_depth.permute(1, 2, 0).numpy() - coarse).max()
    assert err < 0.02 * np.abs(coarse).max()


def test_resize_mask_and_intrinsics() -> None:
    mask = np.zeros((8, 8), bool)
    mask[:, :3] = True  # three of the four left columns
    defined = np.ones((8, 8), bool)
    defined[:, :3] = False  # ... but only the fourth, unset, column is defined
    np.testing.assert_array_equal(transforms.resize_mask(mask, 1, 2), [[True, False]])
    np.testing.assert_array_equal(transforms.resize_mask(mask, 1, 2, defined), [[False, False]])
    K = transforms.resize_intrinsics([725.0, 725.0, 620.5, 187.0], (375, 1242), (48, 128))
    expected = geometry.scale_intrinsics(
        torch.tensor([725.0, 725.0, 620.5, 187.0]), 128 / 1242, 48 / 375
    )
    torch.testing.assert_close(K, expected)


def test_holdout_ranges_are_a_contiguous_disjoint_tail() -> None:
    train, val = transforms.holdout_ranges(100, 0.05, span=1)
    assert (train, val) == (range(0, 95), range(95, 100))
    train, val = transforms.holdout_ranges(20, 0.01, span=2)  # at least span + 1 frames
    assert (train, val) == (range(0, 17), range(17, 20))
    assert transforms.holdout_ranges(10, 0.0) == (range(0, 10), range(10, 10))


# --------------------------------------------------------------------------------------------
# Sizes read from the header, before decoding
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "read",
    [
        flow_io.read_kitti_flow_png,
        flow_io.read_vkitti_flow_png,
        flow_io.read_vkitti_depth,
        flow_io.read_rgb,
        flow_io.image_size,
        flow_io.read_flow,
    ],
)
def test_a_png_header_claiming_30000_by_30000_is_refused_before_decoding(
    tmp_path: Path, read
) -> None:
    """OpenCV tried to allocate 5.4 GB for it and cv2.error escaped ``_decode_png``."""
    path = tmp_path / "huge.png"
    path.write_bytes(png_header_only(30_000, 30_000, depth=16, channels=3))
    with pytest.raises(DataFileError) as err:
        read(path)
    assert str(err.value) == (
        f"{path}: the header claims 30000×30000 pixels, more than the 33,554,432 a reader "
        "decodes (mfg_lightning.flow.io.MAX_PIXELS): corrupt?"
    )


def test_an_npy_header_claiming_1e5_by_1e5_is_refused_before_reading(tmp_path: Path) -> None:
    """np.load raised an uncaught MemoryError (149 GiB) for it."""
    path = tmp_path / "huge.npy"
    path.write_bytes(npy_header_only((100_000, 100_000, 2)))
    with pytest.raises(DataFileError, match=rf"^{path}: the header claims 100000×100000 pixels"):
        flow_io.read_npy_flow(path)
    # a header that fits but whose data is short is called truncated, naming both sizes
    path.write_bytes(npy_header_only((4, 5, 2), "<f4", b"\0" * 100))
    with pytest.raises(DataFileError, match=r"truncated: 228 bytes, its header's \(4, 5, 2\)"):
        flow_io.read_npy_flow(path)


def test_sizes_other_than_the_datasets_frames_are_refused_before_decoding(tmp_path: Path) -> None:
    flow = _random_flow(7, 11)
    flow_io.write_vkitti_flow_png(tmp_path / "f.png", flow)
    flow_io.write_flo(tmp_path / "f.flo", flow)
    flow_io.write_npy_flow(tmp_path / "f.npy", flow)
    for name in ("f.png", "f.flo", "f.npy"):
        got, _ = flow_io.read_flow(tmp_path / name, "vkitti", size=(7, 11))
        assert got.shape == (7, 11, 2)
        with pytest.raises(DataFileError) as err:
            flow_io.read_flow(tmp_path / name, "vkitti", size=(375, 1242))
        assert str(err.value) == (
            f"{tmp_path / name}: the header claims 11×7 pixels, but this dataset's frames are "
            "1242×375"
        )


def test_a_directory_where_a_file_should_be_is_not_file_not_found(tmp_path: Path) -> None:
    for name in ("flow.npy", "flow.npz", "flow.flo", "flow.png", "frame.jpg"):
        (tmp_path / name).mkdir()
        read = flow_io.image_size if name.endswith("jpg") else flow_io.read_flow
        with pytest.raises(DataFileError) as err:
            read(tmp_path / name)
        assert str(err.value) == f"{tmp_path / name}: a directory, not a file"


def test_a_decoders_own_errors_become_the_one_line_data_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """OpenCV raises cv2.error (and an allocation MemoryError) instead of returning None for
    some files; what it raises is simulated here, the reading around it is real."""
    flow_io.write_kitti_flow_png(tmp_path / "f.png", _random_flow())
    for error in (cv2.error("OpenCV(4.10) error: (-215:Assertion failed) in imdecode_"),
                  MemoryError()):  # fmt: skip

        def decode(*args, error=error):
            raise error

        monkeypatch.setattr(cv2, "imdecode", decode)
        with pytest.raises(DataFileError, match=rf"^{tmp_path / 'f.png'}: not a readable image"):
            flow_io.read_kitti_flow_png(tmp_path / "f.png")
    # a corrupt .npz (its archive cut short) is one line naming it, not a zipfile error
    np.savez(tmp_path / "f.npz", flow=_random_flow())
    data = (tmp_path / "f.npz").read_bytes()
    (tmp_path / "f.npz").write_bytes(data[: len(data) - 30])
    with pytest.raises(DataFileError, match=rf"^{tmp_path / 'f.npz'}: not a readable numpy file"):
        flow_io.read_npy_flow(tmp_path / "f.npz")
