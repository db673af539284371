"""Calibration on analytically rendered mirror spheres and synthetic ChArUco views."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from polarshape.acquisition.calibrate import (
    CharucoBoardSpec,
    Intrinsics,
    calibrate_intrinsics_charuco,
    calibrate_intrinsics_from_files,
    calibrate_lights_from_files,
    fit_sphere,
    light_directions_from_mirror_sphere,
    mosaic_to_superpixel_intensity,
    update_capture_yaml,
)
from polarshape.errors import ImageError

SS = 4  # supersampling per axis


def _lights() -> np.ndarray:
    """(K, 3) unit directions to the lights, camera frame (z < 0: on the camera's side)."""
    dirs = []
    for zenith, azimuth in [(5, 0), (20, 30), (35, 150), (50, 250), (60, 320), (45, 90)]:
        z, a = math.radians(zenith), math.radians(azimuth)
        dirs.append([math.sin(z) * math.cos(a), math.sin(z) * math.sin(a), -math.cos(z)])
    return np.asarray(dirs)


def _subpixel_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """(H*SS, W*SS) sample coordinates in pixels (pixel centres at integers)."""
    offsets = (np.arange(SS) + 0.5) / SS - 0.5
    u = (np.arange(w)[:, None] + offsets[None, :]).ravel()
    v = (np.arange(h)[:, None] + offsets[None, :]).ravel()
    return np.meshgrid(u, v)


def _shade(normals: np.ndarray, view: np.ndarray, hit: np.ndarray, light: np.ndarray,
           sigma_deg: float = 2.0) -> np.ndarray:
    """Mirror reflection of a small round source (Gaussian, sigma) + a faint ambient term."""
    refl = 2 * np.sum(normals * view, axis=-1, keepdims=True) * normals - view  # (..., 3)
    cos = np.clip(np.sum(refl * light, axis=-1), -1, 1)
    angle = np.degrees(np.arccos(cos))
    return np.where(hit, 0.02 + np.exp(-(angle / sigma_deg) ** 2), 0.0)


def _downsample(samples: np.ndarray, h: int, w: int) -> np.ndarray:
    return samples.reshape(h, SS, w, SS).mean(axis=(1, 3))


def _render_ortho(light: np.ndarray, h: int, w: int, cu: float, cv: float, r: float) -> tuple[np.ndarray, np.ndarray]:
    uu, vv = _subpixel_grid(h, w)
    x, y = (uu - cu) / r, (vv - cv) / r
    hit = x**2 + y**2 < 1
    nz = -np.sqrt(np.clip(1 - x**2 - y**2, 0, None))
    normals = np.stack([x, y, nz], axis=-1)
    view = np.broadcast_to(np.array([0.0, 0.0, -1.0]), normals.shape)
    image = _downsample(_shade(normals, view, hit, light), h, w)
    mask = _downsample(hit.astype(np.float64), h, w) >= 0.5
    return image, mask


def _render_persp(lights: np.ndarray, k: Intrinsics, h: int, w: int, center: np.ndarray,
                  radius: float) -> tuple[list[np.ndarray], np.ndarray]:
    """One image per light (the sphere geometry is ray cast once) and the sphere mask."""
    uu, vv = _subpixel_grid(h, w)
    d = np.stack([(uu - k.cx) / k.fx, (vv - k.cy) / k.fy, np.ones_like(uu)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    b = d @ center
    disc = b**2 - center @ center + radius**2
    hit = disc > 0
    t = b[hit] - np.sqrt(disc[hit])
    normals = (t[:, None] * d[hit] - center) / radius  # (P, 3) on the sphere only
    images = []
    for light in lights:
        samples = np.zeros(hit.shape)
        samples[hit] = _shade(normals, -d[hit], np.ones(len(t), bool), light)
        images.append(_downsample(samples, h, w))
    mask = _downsample(hit.astype(np.float64), h, w) >= 0.5
    return images, mask


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(a * b, axis=-1)))


def test_orthographic_mirror_sphere_directions() -> None:
    lights = _lights()
    h = w = 320
    renders = [_render_ortho(light, h, w, 161.3, 158.6, 140.0) for light in lights]
    mask = renders[0][1]
    sphere = fit_sphere(mask)
    assert sphere.center_uv == pytest.approx((161.3, 158.6), abs=0.1)
    assert sphere.radius_px == pytest.approx(140.0, abs=0.2)
    est = light_directions_from_mirror_sphere([r[0] for r in renders], mask=mask)
    errors = _angles_deg(est, lights)
    assert errors.max() < 0.5, errors
    est_circle = light_directions_from_mirror_sphere([r[0] for r in renders], circle=(161.3, 158.6, 140.0))
    assert _angles_deg(est_circle, lights).max() < 0.5


def test_perspective_mirror_sphere_directions() -> None:
    lights = _lights()
    k = Intrinsics(fx=900.0, fy=905.0, cx=318.4, cy=241.2)
    center, radius = np.array([0.045, -0.02, 0.32]), 0.045
    images, mask = _render_persp(lights, k, 480, 640, center, radius)
    sphere = fit_sphere(mask, k)
    axis_err = _angles_deg(np.asarray(sphere.axis), center / np.linalg.norm(center))
    assert axis_err < 0.05
    assert sphere.half_angle_rad == pytest.approx(math.asin(radius / np.linalg.norm(center)), rel=2e-3)
    est = light_directions_from_mirror_sphere(images, mask=mask, intrinsics=k)
    errors = _angles_deg(est, lights)
    assert errors.max() < 0.5, errors
    # ignoring perspective costs several degrees here: the test can tell the two apart
    ortho = light_directions_from_mirror_sphere(images, mask=mask)
    assert _angles_deg(ortho, lights).max() > 1.0


def test_lights_from_mosaic_files_into_capture_yaml(tmp_path: Path) -> None:
    lights = _lights()[:3]
    paths = []
    for i, light in enumerate(lights):
        image, mask = _render_ortho(light, 400, 400, 201.0, 198.0, 170.0)
        # a polarised highlight: the four polariser sites see different fractions; their mean is the intensity
        gains = np.array([[1.3, 0.85], [0.7, 1.15]])
        mosaic = np.rint(image * np.tile(gains, (200, 200)) * 3000).astype(np.uint16)
        paths.append(tmp_path / f"{i:03d}.png")
        cv2.imwrite(str(paths[-1]), mosaic)
    cv2.imwrite(str(tmp_path / "mask.png"), mask.astype(np.uint8) * 255)
    capture = tmp_path / "capture.yaml"
    capture.write_text(yaml.safe_dump({
        "format": "polarshape-capture/1",
        "camera": {"model": "x", "projection": "orthographic", "bit_depth": 12},
        "lights": [{"position": [0, 0, -1], "intensity": 1.0, "frame": f"frames/{i:03d}.png"} for i in range(3)],
    }, sort_keys=False))
    est = calibrate_lights_from_files(paths, mask_path=tmp_path / "mask.png", mosaic=True, capture_yaml=tmp_path)
    assert _angles_deg(est, lights).max() < 0.5
    doc = yaml.safe_load(capture.read_text())
    for entry, light in zip(doc["lights"], lights, strict=True):
        assert "position" not in entry and entry["intensity"] == 1.0
        assert _angles_deg(np.asarray(entry["direction"]), light) < 0.5
    with pytest.raises(ValueError, match="2 light directions for the 3 lights"):
        update_capture_yaml(capture, lights=est[:2])
    with pytest.raises(ValueError, match="exactly one of mask"):
        light_directions_from_mirror_sphere([np.zeros((4, 4))])


def _mosaic_files(tmp_path: Path, lights: np.ndarray, size: int = 160) -> tuple[list[Path], np.ndarray]:
    """Raw-mosaic PNGs of an orthographic mirror sphere, one per light, and its (size, size) raw mask."""
    paths, mask = [], None
    for i, light in enumerate(lights):
        image, mask = _render_ortho(light, size, size, size / 2 + 0.7, size / 2 - 1.3, 0.42 * size)
        paths.append(tmp_path / f"{i:03d}.png")
        cv2.imwrite(str(paths[-1]), np.rint(image * 3000).astype(np.uint16))
    return paths, mask


def test_a_superpixel_mask_like_a_captures_mask_png_is_accepted(tmp_path: Path) -> None:
    lights = _lights()[:2]
    paths, raw_mask = _mosaic_files(tmp_path, lights)
    cv2.imwrite(str(tmp_path / "raw_mask.png"), raw_mask.astype(np.uint8) * 255)
    superpixel_mask = mosaic_to_superpixel_intensity(raw_mask) >= 0.5  # (80, 80), as polarshape writes mask.png
    cv2.imwrite(str(tmp_path / "mask.png"), superpixel_mask.astype(np.uint8) * 255)
    from_raw = calibrate_lights_from_files(paths, mask_path=tmp_path / "raw_mask.png")
    from_superpixels = calibrate_lights_from_files(paths, mask_path=tmp_path / "mask.png")
    assert _angles_deg(from_superpixels, lights).max() < 0.5
    assert _angles_deg(from_superpixels, from_raw).max() < 0.2
    plain = calibrate_lights_from_files(paths, mask_path=tmp_path / "mask.png", mosaic=False)
    assert _angles_deg(plain, lights).max() < 0.5


def test_a_mask_of_another_size_names_both_sizes(tmp_path: Path) -> None:
    paths, _ = _mosaic_files(tmp_path, _lights()[:1])
    cv2.imwrite(str(tmp_path / "mask.png"), np.full((100, 120), 255, dtype=np.uint8))
    with pytest.raises(ImageError, match=r"sphere mask .*mask.png: 120x100 pixels; it must be the images' size 160x160 "
                                         r"or the super-pixel size 80x80"):
        calibrate_lights_from_files(paths, mask_path=tmp_path / "mask.png")


# -- ChArUco ----------------------------------------------------------------------------------------


def _rodrigues(rx: float, ry: float, rz: float) -> np.ndarray:
    r, _ = cv2.Rodrigues(np.radians([rx, ry, rz]))
    return r


def _render_board(spec: CharucoBoardSpec, k: np.ndarray, rotation: np.ndarray, t: np.ndarray,
                  size: tuple[int, int], ss: int = 3) -> np.ndarray:
    """View of the board plane (X right, Y down, Z = 0; metres) under K [R | t], anti-aliased."""
    board = spec.board()
    px_per_m = 6000.0
    cols, rows = spec.squares
    texture = board.generateImage((int(cols * spec.square_length_m * px_per_m),
                                   int(rows * spec.square_length_m * px_per_m)), marginSize=0, borderBits=1)
    texture = cv2.copyMakeBorder(texture, 0, 0, 0, 0, cv2.BORDER_CONSTANT)
    # texture pixel centre (i, j) <-> board point ((j + 0.5) / s, (i + 0.5) / s)
    board_from_tex = np.array([[1 / px_per_m, 0, 0.5 / px_per_m], [0, 1 / px_per_m, 0.5 / px_per_m], [0, 0, 1]])
    k_ss = k.copy()
    k_ss[:2] *= ss
    k_ss[0, 2] = ss * k[0, 2] + (ss - 1) / 2
    k_ss[1, 2] = ss * k[1, 2] + (ss - 1) / 2
    img_from_board = k_ss @ np.column_stack([rotation[:, 0], rotation[:, 1], t])
    h = img_from_board @ board_from_tex
    w, hgt = size
    big = cv2.warpPerspective(texture, h, (w * ss, hgt * ss), flags=cv2.INTER_LINEAR, borderValue=200)
    return cv2.resize(big, (w, hgt), interpolation=cv2.INTER_AREA)


POSES = [(0, 0, 0, 0.0, 0.0), (25, 0, 5, 0.02, 0.01), (-25, 10, -5, -0.02, 0.0), (10, 30, 0, 0.0, -0.02),
         (-15, -30, 10, 0.03, 0.02), (30, 20, -10, -0.01, -0.01), (-20, 25, 3, 0.01, 0.03)]


def _views(spec: CharucoBoardSpec, k: np.ndarray, size: tuple[int, int], distance: float) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    board_w = spec.squares[0] * spec.square_length_m
    board_h = spec.squares[1] * spec.square_length_m
    images = []
    for rx, ry, rz, dx, dy in POSES:
        rot = _rodrigues(rx, ry, rz)
        # put the board centre on the optical axis (plus an offset) at `distance`
        centre = np.array([board_w / 2, board_h / 2, 0.0])
        t = np.array([dx, dy, distance]) - rot @ centre
        img = _render_board(spec, k, rot, t, size).astype(np.float64)
        img += rng.normal(0, 2.0, img.shape)
        images.append(np.clip(img, 0, 255).astype(np.uint8))
    return images


def test_charuco_intrinsics_within_one_percent() -> None:
    spec = CharucoBoardSpec(squares=(7, 5), square_length_m=0.03, marker_length_m=0.022)
    k = np.array([[820.0, 0, 327.3], [0, 812.0, 236.8], [0, 0, 1]])
    result = calibrate_intrinsics_charuco(_views(spec, k, (640, 480), 0.42), spec)
    assert result.n_views == len(POSES)
    assert result.fx == pytest.approx(820.0, rel=0.01)
    assert result.fy == pytest.approx(812.0, rel=0.01)
    assert result.cx == pytest.approx(327.3, abs=6.0) and result.cy == pytest.approx(236.8, abs=6.0)
    assert result.rms_px < 0.5


def test_charuco_from_mosaic_files_in_raw_pixels(tmp_path: Path) -> None:
    spec = CharucoBoardSpec(squares=(7, 5), square_length_m=0.03, marker_length_m=0.022)
    k_raw = np.array([[1640.0, 0, 655.1], [0, 1630.0, 470.3], [0, 0, 1]])
    paths = []
    for i, view in enumerate(_views(spec, k_raw, (1312, 960), 0.42)):
        paths.append(tmp_path / f"board{i}.png")
        cv2.imwrite(str(paths[-1]), view.astype(np.uint16) * 16)  # 12-bit counts in a 16-bit PNG
    capture = tmp_path / "capture.yaml"
    capture.write_text(yaml.safe_dump({"format": "polarshape-capture/1", "camera": {"projection": "orthographic"},
                                       "lights": []}))
    result = calibrate_intrinsics_from_files(paths, spec, mosaic=True, capture_yaml=capture)
    assert result.fx == pytest.approx(1640.0, rel=0.01) and result.fy == pytest.approx(1630.0, rel=0.01)
    doc = yaml.safe_load(capture.read_text())
    assert doc["camera"]["projection"] == "perspective"
    assert doc["camera"]["intrinsics"]["fx"] == pytest.approx(result.fx)
    assert len(doc["camera"]["distortion"]) == 5


def test_superpixel_conversion_and_errors() -> None:
    k = Intrinsics(fx=1000.0, fy=990.0, cx=611.5, cy=511.5)
    back = k.raw_to_superpixel().superpixel_to_raw()
    assert (back.fx, back.fy, back.cx, back.cy) == pytest.approx((1000.0, 990.0, 611.5, 511.5))
    mosaic = np.arange(16, dtype=np.uint16).reshape(4, 4)
    np.testing.assert_allclose(mosaic_to_superpixel_intensity(mosaic), [[2.5, 4.5], [10.5, 12.5]])
    with pytest.raises(ValueError, match="even H and W"):
        mosaic_to_superpixel_intensity(np.zeros((3, 4)))
    with pytest.raises(ValueError, match="need >= 3"):
        calibrate_intrinsics_charuco([np.zeros((100, 100), np.uint8)] * 3)
