"""Tests of polarshape.io.export: normal-map PNG conventions, EXR, NPY, parameter maps, no overwrite."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from polarshape.io.export import (
    read_exr,
    read_normal_map_png,
    read_normals_exr,
    write_exr,
    write_normal_map_png,
    write_normals_exr,
    write_npy,
    write_scalar_map_png,
)
from polarshape.io.atomic import OutputExistsError


def _normals(h: int = 20, w: int = 30, seed: int = 0) -> np.ndarray:
    """Random camera-facing unit normals (n_z < 0), NaN background in a corner."""
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(h, w, 3))
    n[..., 2] = -np.abs(n[..., 2])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[:4, :5] = np.nan
    n[5, 5] = (1.0, 0.0, 0.0)  # extreme components: −1 and +1 must survive the round trip
    n[5, 6] = (0.0, -1.0, 0.0)
    return n


def _raw_rgb(path: Path) -> np.ndarray:
    """The PNG's channels as stored, in R, G, B(, A) order (OpenCV reads B, G, R(, A))."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return image[..., [2, 1, 0, *range(3, image.shape[2])]]


@pytest.mark.parametrize("convention", ["opencv", "opengl"])
def test_normal_map_round_trip_within_quantisation(tmp_path: Path, convention: str) -> None:
    n = _normals()
    path = write_normal_map_png(n, tmp_path / "normal_map.png", convention=convention)
    back = read_normal_map_png(path, convention)
    valid = np.all(np.isfinite(n), axis=2)
    assert np.all(np.isnan(back[~valid])) and np.all(np.isfinite(back[valid]))
    assert np.abs(back[valid] - n[valid]).max() <= 1.0 / 65535 + 1e-12
    raw = _raw_rgb(path)
    assert raw.dtype == np.uint16 and raw.shape == (20, 30, 4)
    assert np.all(raw[:4, :5] == 0)  # background: RGB 0 and alpha 0
    np.testing.assert_array_equal(raw[..., 3], np.where(valid, 65535, 0))


def test_normal_map_conventions_are_the_documented_ones(tmp_path: Path) -> None:
    n = np.array([[[0.0, 0.0, -1.0], [0.0, -0.6, -0.8]]])  # frontal; tilted towards the image top
    cv = _raw_rgb(write_normal_map_png(n, tmp_path / "cv.png", convention="opencv"))[..., :3]
    gl = _raw_rgb(write_normal_map_png(n, tmp_path / "gl.png", convention="opengl"))[..., :3]
    # opencv: (n + 1)/2 of the camera frame (y down, z forward): frontal = (½, ½, 0)
    np.testing.assert_array_equal(cv[0, 0], [32768, 32768, 0])
    np.testing.assert_allclose(cv[0, 1], [32768, 0.2 * 65535, 0.1 * 65535], atol=1)
    # opengl: y up, z towards the viewer: frontal = (½, ½, 1), a top-facing tilt has G > ½
    np.testing.assert_array_equal(gl[0, 0], [32768, 32768, 65535])
    np.testing.assert_allclose(gl[0, 1], [32768, 0.8 * 65535, 0.9 * 65535], atol=1)
    # reading with the wrong convention flips y and z
    wrong = read_normal_map_png(tmp_path / "gl.png", "opencv")
    np.testing.assert_allclose(wrong[0, 1], [0.0, 0.6, 0.8], atol=2e-5)


def test_normal_map_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        write_normal_map_png(np.zeros((4, 4)), tmp_path / "a.png")
    with pytest.raises(ValueError, match="convention"):
        write_normal_map_png(_normals(), tmp_path / "a.png", convention="directx")
    cv2.imwrite(str(tmp_path / "grey.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match="16-bit RGB"):
        read_normal_map_png(tmp_path / "grey.png")
    with pytest.raises(FileNotFoundError):
        read_normal_map_png(tmp_path / "missing.png")


def test_rgb_normal_map_without_alpha_still_reads(tmp_path: Path) -> None:
    n = _normals()
    path = write_normal_map_png(n, tmp_path / "rgb.png", convention="opengl", alpha=False)
    assert _raw_rgb(path).shape == (20, 30, 3)
    back = read_normal_map_png(path, "opengl")
    valid = np.all(np.isfinite(n), axis=2)
    assert np.all(np.isnan(back[~valid])) and np.abs(back[valid] - n[valid]).max() <= 1.0 / 65535 + 1e-12


def test_alpha_decides_the_background_of_an_rgba_normal_map(tmp_path: Path) -> None:
    # alpha 0 with an RGB that would decode as a normal: background; alpha 65535 with RGB 0: the
    # normal (−1, −1, −1) as written (an RGB file could not tell it from the background)
    image = np.zeros((2, 2, 4), np.uint16)
    image[0, 0] = (32768, 32768, 0, 0)
    image[0, 1] = (0, 0, 0, 65535)
    image[1, :] = (32768, 32768, 0, 65535)
    cv2.imwrite(str(tmp_path / "rgba.png"), image[..., [2, 1, 0, 3]])
    back = read_normal_map_png(tmp_path / "rgba.png")
    assert np.isnan(back[0, 0]).all()
    np.testing.assert_allclose(back[0, 1], [-1.0, -1.0, -1.0])
    np.testing.assert_allclose(back[1], [[0.0, 0.0, -1.0]] * 2, atol=2e-5)


def test_normals_exr_has_an_alpha_channel_matching_the_mask(tmp_path: Path) -> None:
    n = _normals().astype(np.float32)
    mask = np.all(np.isfinite(n), axis=2)
    mask[10:12, 10:12] = False  # masked out although the normal is finite
    write_normals_exr(n, tmp_path / "normals.exr", mask)
    array, names = read_exr(tmp_path / "normals.exr")
    assert names == ("R", "G", "B", "A") and array.dtype == np.float32
    np.testing.assert_array_equal(array[..., 3], mask.astype(np.float32))
    np.testing.assert_array_equal(array[mask][:, :3], n[mask])
    assert np.all(array[~mask] == 0)  # associated alpha: no NaN to spread through filters
    normals, inside = read_normals_exr(tmp_path / "normals.exr")
    np.testing.assert_array_equal(inside, mask)
    assert np.isnan(normals[~mask]).all()
    np.testing.assert_array_equal(normals[mask], n[mask])
    write_exr(n, tmp_path / "old.exr")  # an RGB file without A: the finite normals are the mask
    assert np.array_equal(read_normals_exr(tmp_path / "old.exr")[1], np.all(np.isfinite(n), axis=2))
    with pytest.raises(ValueError, match="mask must have shape"):
        write_normals_exr(n, tmp_path / "bad.exr", mask[:-1])


def test_exr_round_trip_is_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    a = rng.normal(size=(17, 23, 5)).astype(np.float32)
    a[0, 0, 0] = np.nan
    a[1, 1, 1] = 1e-30
    names = ("depth", "N.x", "N.y", "N.z", "albedo")
    write_exr(a, tmp_path / "maps.exr", channel_names=names)
    back, got_names = read_exr(tmp_path / "maps.exr")
    assert got_names == names and back.dtype == np.float32
    np.testing.assert_array_equal(back, a)  # NaN positions compare equal


def test_exr_default_channel_names_and_2d(tmp_path: Path) -> None:
    rgb = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    write_exr(rgb, tmp_path / "rgb.exr")
    back, names = read_exr(tmp_path / "rgb.exr")
    assert names == ("R", "G", "B")
    np.testing.assert_array_equal(back, rgb)
    write_exr(rgb[..., 0], tmp_path / "depth.exr")
    back, names = read_exr(tmp_path / "depth.exr")
    assert names == ("Y",) and back.shape == (2, 3, 1)
    with pytest.raises(ValueError, match="channel_names"):
        write_exr(rgb, tmp_path / "bad.exr", channel_names=("a", "a", "b"))
    with pytest.raises(ValueError, match=r"\.exr"):
        write_exr(rgb, tmp_path / "bad.png")


def test_npy_round_trip(tmp_path: Path) -> None:
    n = _normals().astype(np.float32)
    path = write_npy(n, tmp_path / "normals.npy")
    np.testing.assert_array_equal(np.load(path), n)
    assert not list(tmp_path.glob(".*"))
    with pytest.raises(ValueError, match=r"\.npy"):
        write_npy(n, tmp_path / "normals.bin")


def test_scalar_map_grey_and_colour(tmp_path: Path) -> None:
    v = np.array([[0.0, 0.5, 1.0, 2.0], [np.nan, -1.0, 0.25, 0.75]])
    grey = _raw_rgb_or_grey(write_scalar_map_png(v, tmp_path / "g.png", 0.0, 1.0))
    assert grey.dtype == np.uint16
    np.testing.assert_array_equal(grey, [[0, 32768, 65535, 65535], [0, 0, 16384, 49151]])
    colour = _raw_rgb(write_scalar_map_png(v, tmp_path / "c.png", 0.0, 1.0, colormap="viridis"))
    assert colour.dtype == np.uint8 and colour.shape == (2, 4, 3)
    from matplotlib import colormaps

    np.testing.assert_array_equal(colour[0, 2], colormaps["viridis"](1.0, bytes=True)[:3])
    np.testing.assert_array_equal(colour[1, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="vmin < vmax"):
        write_scalar_map_png(v, tmp_path / "x.png", 1.0, 1.0)
    with pytest.raises(ValueError, match="unknown matplotlib colormap"):
        write_scalar_map_png(v, tmp_path / "x.png", 0.0, 1.0, colormap="no-such-map")


def _raw_rgb_or_grey(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


@pytest.mark.parametrize(
    "write",
    [
        lambda p, ow: write_normal_map_png(_normals(), p / "n.png", overwrite=ow),
        lambda p, ow: write_npy(np.zeros(3), p / "a.npy", overwrite=ow),
        lambda p, ow: write_exr(np.zeros((2, 2)), p / "a.exr", overwrite=ow),
        lambda p, ow: write_scalar_map_png(np.zeros((2, 2)), p / "s.png", 0.0, 1.0, overwrite=ow),
    ],
    ids=["normal_map", "npy", "exr", "scalar_map"],
)
def test_refuses_to_overwrite_without_permission(tmp_path: Path, write) -> None:
    path = write(tmp_path, False)
    before = path.read_bytes()
    path.write_bytes(b"user data")
    with pytest.raises(OutputExistsError):
        write(tmp_path, False)
    assert path.read_bytes() == b"user data"
    write(tmp_path, True)
    assert path.read_bytes() == before
