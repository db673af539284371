"""Calibration: light directions from a mirror sphere, camera intrinsics from ChArUco boards.

Conventions (spec section 1): camera frame x right, y down, z forward; pixel (u, v) = (column,
row) with pixel centres at integer coordinates (OpenCV); a light direction L is the unit vector
from the scene *to* the light, so lights beside the camera have L_z < 0.

1. **Light directions** (:func:`light_directions_from_mirror_sphere`). A mirror sphere lit by one
   distant light shows a highlight where the sphere normal n bisects the view direction V (surface
   to camera) and L: L = 2 (n·V) n − V. The sphere is found from a mask (its silhouette edge is
   fitted: a circle for an orthographic camera, a cone of rays for a perspective one) or given as
   a circle; the highlight is the intensity-weighted centroid of the brightest blob on the sphere.
2. **Intrinsics** (:func:`calibrate_intrinsics_charuco`). ChArUco corners are detected with
   ``cv2.aruco.CharucoDetector`` in several views of a board and ``cv2.calibrateCamera`` fits
   fx, fy, cx, cy and distortion (OpenCV order k1, k2, p1, p2, k3).

Both work on raw polarisation mosaics too (``mosaic=True``): the 2x2 polariser blocks are
averaged into a super-pixel intensity image (the polarised highlight of a mirror sphere would
otherwise be modulated by the polariser pattern) and the results are mapped back to raw-mosaic
pixels (u_raw = 2 u_sp + 0.5), the unit of capture.yaml.

:func:`update_capture_yaml` writes the results into a capture folder's ``capture.yaml``
(``lights[*].direction``, ``camera.intrinsics``/``distortion``) atomically.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from pydantic import Field
from scipy import ndimage

from polarshape.cameras import intrinsic_matrix, normalised_coordinates
from polarshape.errors import CaptureError, ImageError
from polarshape.io.capture import IntrinsicsSpec, edit_capture_yaml, set_light_directions

logger = logging.getLogger(__name__)

__all__ = [
    "CharucoBoardSpec",
    "Intrinsics",
    "SphereImage",
    "calibrate_intrinsics_charuco",
    "calibrate_intrinsics_from_files",
    "calibrate_lights_from_files",
    "find_highlight",
    "fit_sphere",
    "light_direction_from_highlight",
    "light_directions_from_mirror_sphere",
    "mosaic_to_superpixel_intensity",
    "sphere_mask_from_image",
    "update_capture_yaml",
]


# -- data ------------------------------------------------------------------------------------------


class Intrinsics(IntrinsicsSpec):
    """Pinhole intrinsics as calibrated: the capture format's ``camera.intrinsics``
    (:class:`~polarshape.io.capture.IntrinsicsSpec`: fx, fy, cx, cy in pixels, pixel centres at
    integers) with the OpenCV distortion and the quality of the calibration.

    Attributes:
        distortion: (k1, k2, p1, p2, k3), or empty.
        rms_px: reprojection RMS of the calibration, pixels (NaN if not calibrated here).
        n_views: number of views used.
    """

    distortion: tuple[float, ...] = ()
    rms_px: float = Field(float("nan"), allow_inf_nan=True)  # NaN is meaningful here (capture.yaml floats are finite)
    n_views: int = 0

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], distortion: Sequence[float] = ()) -> Intrinsics:
        """From ``{fx, fy, cx, cy}`` (capture.yaml's ``camera.intrinsics``)."""
        missing = [k for k in IntrinsicsSpec.model_fields if k not in data]
        if missing:
            raise ValueError(f"intrinsics are missing {missing}; give fx, fy, cx, cy in pixels")
        return cls(fx=float(data["fx"]), fy=float(data["fy"]), cx=float(data["cx"]), cy=float(data["cy"]),
                   distortion=tuple(float(d) for d in distortion))

    def matrix(self) -> np.ndarray:
        """(3, 3) camera matrix K."""
        return intrinsic_matrix(self.fx, self.fy, self.cx, self.cy)

    def to_capture_dict(self) -> dict[str, float]:
        """``camera.intrinsics`` of capture.yaml (the :class:`~polarshape.io.capture.IntrinsicsSpec` fields)."""
        return self.model_dump(include=set(IntrinsicsSpec.model_fields))

    def superpixel_to_raw(self) -> Intrinsics:
        """Intrinsics of super-pixel images (2x2 block means) expressed in raw-mosaic pixels."""
        return Intrinsics(fx=2 * self.fx, fy=2 * self.fy, cx=2 * self.cx + 0.5, cy=2 * self.cy + 0.5,
                          distortion=self.distortion, rms_px=2 * self.rms_px, n_views=self.n_views)

    def raw_to_superpixel(self) -> Intrinsics:
        """Inverse of :meth:`superpixel_to_raw`."""
        return Intrinsics(fx=self.fx / 2, fy=self.fy / 2, cx=(self.cx - 0.5) / 2, cy=(self.cy - 0.5) / 2,
                          distortion=self.distortion, rms_px=self.rms_px / 2, n_views=self.n_views)


@dataclass(frozen=True)
class SphereImage:
    """Where a sphere appears in the image.

    Attributes:
        center_uv: centre of the fitted silhouette circle (orthographic) or the projection of
            the sphere centre (perspective), pixels.
        radius_px: silhouette radius, pixels (orthographic; the mean for perspective).
        axis: perspective only: (3,) unit ray from the camera to the sphere centre, camera frame.
        half_angle_rad: perspective only: half-angle of the silhouette cone.
    """

    center_uv: tuple[float, float]
    radius_px: float
    axis: tuple[float, float, float] | None = None
    half_angle_rad: float | None = None


# -- sphere and highlight --------------------------------------------------------------------------


def _edge_points(mask: np.ndarray) -> np.ndarray:
    """(P, 2) (u, v) points on the silhouette edge: midpoints between 4-adjacent in/out pixels."""
    m = mask.astype(bool)
    rows, cols = np.nonzero(m[:, :-1] != m[:, 1:])  # horizontal neighbours differ
    horizontal = np.stack([cols + 0.5, rows.astype(np.float64)], axis=1)
    rows, cols = np.nonzero(m[:-1, :] != m[1:, :])  # vertical neighbours differ
    vertical = np.stack([cols.astype(np.float64), rows + 0.5], axis=1)
    return np.concatenate([horizontal, vertical], axis=0)


def _rays(uv: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """(P, 3) unit camera-frame rays through pixels ``uv`` (P, 2), undistorted."""
    k = intrinsics
    norm = normalised_coordinates(uv.reshape(-1, 2), k.fx, k.fy, k.cx, k.cy, k.distortion)  # (P, 2)
    rays = np.concatenate([norm, np.ones((norm.shape[0], 1))], axis=1)  # (P, 3)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def fit_sphere(mask: np.ndarray, intrinsics: Intrinsics | None = None) -> SphereImage:
    """Fit the sphere's silhouette in a (H, W) boolean mask (non-zero = sphere).

    Orthographic (``intrinsics=None``): algebraic least-squares circle through the edge points.
    Perspective: the edge rays form a cone around the ray to the sphere centre; the plane fit
    n·d = cos(alpha) of the unit edge rays d gives its axis n and half-angle alpha.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"sphere mask must have shape (H, W); got {mask.shape}")
    pts = _edge_points(mask != 0)  # (P, 2)
    if pts.shape[0] < 12:
        raise ValueError(f"the sphere mask has only {pts.shape[0]} edge points; is the sphere in the mask?")
    u, v = pts[:, 0], pts[:, 1]
    a = np.stack([u, v, np.ones_like(u)], axis=1)
    sol, *_ = np.linalg.lstsq(a, -(u**2 + v**2), rcond=None)
    cu, cv = -sol[0] / 2, -sol[1] / 2
    radius = float(np.sqrt(max(cu**2 + cv**2 - sol[2], 0.0)))
    if intrinsics is None:
        return SphereImage((float(cu), float(cv)), radius)
    d = _rays(pts, intrinsics)  # (P, 3)
    mean = d.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((d - mean).T))
    axis = vecs[:, 0]  # smallest eigenvalue: normal of the plane of the ray tips
    cos_alpha = float(axis @ mean)
    if cos_alpha < 0:
        axis, cos_alpha = -axis, -cos_alpha
    center_uv = (intrinsics.fx * axis[0] / axis[2] + intrinsics.cx, intrinsics.fy * axis[1] / axis[2] + intrinsics.cy)
    return SphereImage((float(center_uv[0]), float(center_uv[1])), radius,
                       (float(axis[0]), float(axis[1]), float(axis[2])), float(math.acos(min(1.0, cos_alpha))))


def sphere_mask_from_image(image: np.ndarray, threshold: float | None = None) -> np.ndarray:
    """Segment a sphere that is brighter than the background (e.g. under ambient light).

    Args:
        image: (H, W) intensities.
        threshold: intensity threshold; default Otsu's.

    Returns:
        (H, W) boolean mask of the largest bright blob, holes filled.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must have shape (H, W); got {img.shape}")
    if threshold is None:
        t, _ = cv2.threshold(_rescale_to_uint8(img), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        threshold = img.min() + t / 255.0 * (img.max() - img.min())
    labels, n = ndimage.label(img > threshold)
    if n == 0:
        raise ValueError("no bright region found for the sphere; give a mask or a circle instead")
    sizes = ndimage.sum(np.ones_like(img), labels, index=np.arange(1, n + 1))
    return ndimage.binary_fill_holes(labels == (int(np.argmax(sizes)) + 1))


def _disk(shape: tuple[int, int], sphere: SphereImage, shrink: float) -> np.ndarray:
    vv, uu = np.mgrid[0:shape[0], 0:shape[1]]
    return (uu - sphere.center_uv[0]) ** 2 + (vv - sphere.center_uv[1]) ** 2 <= (shrink * sphere.radius_px) ** 2


def find_highlight(image: np.ndarray, sphere: SphereImage, *, relative_threshold: float = 0.5,
                   min_contrast: float = 3.0, mask: np.ndarray | None = None) -> tuple[float, float]:
    """Intensity-weighted centroid (u, v) of the brightest blob on the sphere.

    Args:
        image: (H, W) intensities of the mirror sphere under one light.
        sphere: the sphere's image (:func:`fit_sphere`).
        relative_threshold: blob = connected pixels above this fraction of the peak.
        min_contrast: the peak must exceed this multiple of the median on the sphere.
        mask: optional (H, W) sphere mask; default: the fitted disk (shrunk by 2 %).

    Raises:
        ValueError: if there is no clear highlight (light behind the sphere, wrong image).
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must have shape (H, W); got {img.shape}")
    region = _disk(img.shape, sphere, 0.98) if mask is None else (np.asarray(mask) != 0)
    values = np.where(region, img, -np.inf)
    peak_index = np.unravel_index(int(np.argmax(values)), img.shape)
    peak = float(img[peak_index])
    background = float(np.median(img[region]))
    if not peak > min_contrast * max(background, 1e-12):
        raise ValueError(f"no highlight on the sphere: peak {peak:.4g} is not {min_contrast}x above the "
                         f"median {background:.4g} (is the light behind the sphere, or the image overexposed?)")
    threshold = background + relative_threshold * (peak - background)
    labels, _ = ndimage.label((img >= threshold) & region)
    blob = labels == labels[peak_index]
    weights = np.where(blob, img - background, 0.0)
    vv, uu = np.nonzero(blob)
    w = weights[vv, uu]
    return float((uu * w).sum() / w.sum()), float((vv * w).sum() / w.sum())


def light_direction_from_highlight(highlight_uv: tuple[float, float], sphere: SphereImage,
                                   intrinsics: Intrinsics | None = None) -> np.ndarray:
    """Unit direction (3,) to the light, camera frame, from a highlight on a mirror sphere.

    Orthographic: V = (0, 0, -1); n from the highlight's offset in the silhouette circle.
    Perspective: the highlight ray d meets the sphere (centre on ``sphere.axis``, unit radius,
    distance 1/sin(alpha)) at P; n = P − C, V = −d. Then L = 2 (n·V) n − V.
    """
    u, v = highlight_uv
    if intrinsics is None:
        x = (u - sphere.center_uv[0]) / sphere.radius_px
        y = (v - sphere.center_uv[1]) / sphere.radius_px
        r2 = x * x + y * y
        if r2 >= 1.0:
            raise ValueError(f"highlight ({u:.1f}, {v:.1f}) lies outside the sphere's silhouette")
        n = np.array([x, y, -math.sqrt(1.0 - r2)])
        view = np.array([0.0, 0.0, -1.0])
    else:
        if sphere.axis is None or sphere.half_angle_rad is None:
            raise ValueError("perspective light calibration needs a sphere fitted with intrinsics (fit_sphere)")
        center = np.asarray(sphere.axis) / math.sin(sphere.half_angle_rad)  # (3,), sphere radius 1
        d = _rays(np.array([[u, v]]), intrinsics)[0]  # (3,)
        b = float(d @ center)
        disc = b * b - float(center @ center) + 1.0
        if disc < 0:
            raise ValueError(f"the ray through the highlight ({u:.1f}, {v:.1f}) misses the fitted sphere")
        point = (b - math.sqrt(disc)) * d
        n = point - center
        n /= np.linalg.norm(n)
        view = -d
    light = 2.0 * float(n @ view) * n - view
    return light / np.linalg.norm(light)


def light_directions_from_mirror_sphere(
    images: Sequence[np.ndarray],
    *,
    mask: np.ndarray | None = None,
    circle: tuple[float, float, float] | None = None,
    intrinsics: Intrinsics | None = None,
    relative_threshold: float = 0.5,
) -> np.ndarray:
    """Light directions from K images of a mirror sphere, one light on in each.

    Args:
        images: K (H, W) intensity images (use :func:`mosaic_to_superpixel_intensity` on raw
            polarisation mosaics first).
        mask: (H, W) sphere mask (non-zero = sphere), fitted by :func:`fit_sphere`; or
        circle: ``(cu, cv, radius)`` in pixels (orthographic only).
        intrinsics: None for an orthographic camera, else the pinhole intrinsics of ``images``.
        relative_threshold: see :func:`find_highlight`.

    Returns:
        (K, 3) unit vectors to the lights, camera frame.
    """
    if (mask is None) == (circle is None):
        raise ValueError("give exactly one of mask (sphere silhouette) or circle (cu, cv, radius)")
    if circle is not None:
        if intrinsics is not None:
            raise ValueError("a circle describes an orthographic sphere image; give a mask for a perspective camera")
        sphere = SphereImage((float(circle[0]), float(circle[1])), float(circle[2]))
    else:
        sphere = fit_sphere(np.asarray(mask), intrinsics)
    logger.info("mirror sphere at (%.1f, %.1f), radius %.1f px", *sphere.center_uv, sphere.radius_px)
    # search the highlight inside the silhouette, away from its anti-aliased rim
    region = None if mask is None else ndimage.binary_erosion(np.asarray(mask) != 0, iterations=2)
    directions = []
    for k, image in enumerate(images):
        try:
            uv = find_highlight(image, sphere, relative_threshold=relative_threshold, mask=region)
        except ValueError as exc:
            raise ValueError(f"image {k}: {exc}") from exc
        directions.append(light_direction_from_highlight(uv, sphere, intrinsics))
    return np.stack(directions, axis=0)


# -- intrinsics ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CharucoBoardSpec:
    """A ChArUco board: ``squares`` = (columns, rows); lengths in metres; an OpenCV dictionary."""

    squares: tuple[int, int] = (7, 5)
    square_length_m: float = 0.04
    marker_length_m: float = 0.03
    dictionary: str = "DICT_5X5_100"
    legacy_pattern: bool = False

    def board(self) -> Any:
        """The ``cv2.aruco.CharucoBoard``."""
        aruco = cv2.aruco
        if not hasattr(aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_5X5_100, DICT_6X6_250)")
        if not 0 < self.marker_length_m < self.square_length_m:
            raise ValueError(f"marker_length_m ({self.marker_length_m}) must be > 0 and < square_length_m "
                             f"({self.square_length_m})")
        board = aruco.CharucoBoard(tuple(self.squares), self.square_length_m, self.marker_length_m,
                                   aruco.getPredefinedDictionary(getattr(aruco, self.dictionary)))
        board.setLegacyPattern(self.legacy_pattern)
        return board


def _rescale_to_uint8(image: np.ndarray) -> np.ndarray:
    """Map the (H, W) image's [min, max] linearly to [0, 255] ``uint8``."""
    img = np.asarray(image, dtype=np.float64)
    lo, hi = float(img.min()), float(img.max())
    return np.rint((img - lo) * (255.0 / max(hi - lo, 1e-12))).astype(np.uint8)


def _to_gray8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        img = _rescale_to_uint8(img)
    return img


def calibrate_intrinsics_charuco(
    images: Sequence[np.ndarray],
    board: CharucoBoardSpec = CharucoBoardSpec(),
    *,
    min_corners: int = 8,
    fix_k3: bool = True,
) -> Intrinsics:
    """Camera intrinsics from K >= 3 views of a ChArUco board.

    Args:
        images: (H, W) grey (any dtype, rescaled to 8 bit) or (H, W, 3) BGR images, one size.
        board: the printed board.
        min_corners: views with fewer detected ChArUco corners are skipped.
        fix_k3: keep k3 = 0 (recommended unless the lens is wide-angle).

    Returns:
        :class:`Intrinsics` in the images' pixels, with the reprojection RMS.
    """
    cv_board = board.board()
    detector = cv2.aruco.CharucoDetector(cv_board)
    object_points, image_points = [], []
    size: tuple[int, int] | None = None
    for k, image in enumerate(images):
        gray = _to_gray8(image)
        if size is None:
            size = (gray.shape[1], gray.shape[0])
        elif size != (gray.shape[1], gray.shape[0]):
            raise ValueError(f"image {k} is {gray.shape[1]}x{gray.shape[0]}, the first is {size[0]}x{size[1]}")
        corners, ids, _, _ = detector.detectBoard(gray)
        n = 0 if ids is None else len(ids)
        if n < min_corners:
            logger.warning("image %d: %d ChArUco corners found (< %d); skipped", k, n, min_corners)
            continue
        obj, img = cv_board.matchImagePoints(corners, ids)
        object_points.append(obj.reshape(-1, 3).astype(np.float32))
        image_points.append(img.reshape(-1, 2).astype(np.float32))
    if len(object_points) < 3 or size is None:
        raise ValueError(f"only {len(object_points)} of {len(images)} images show the ChArUco board "
                         f"({board.squares[0]}x{board.squares[1]} squares, {board.dictionary}); need >= 3: check "
                         "the board parameters, focus and lighting")
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    rms, k_matrix, dist, _, _ = cv2.calibrateCamera(object_points, image_points, size, None, None, flags=flags)
    result = Intrinsics(fx=float(k_matrix[0, 0]), fy=float(k_matrix[1, 1]), cx=float(k_matrix[0, 2]),
                        cy=float(k_matrix[1, 2]), distortion=tuple(float(x) for x in np.ravel(dist)[:5]),
                        rms_px=float(rms), n_views=len(object_points))
    logger.info("intrinsics from %d views: fx=%.2f fy=%.2f cx=%.2f cy=%.2f (RMS %.3f px)", result.n_views,
                result.fx, result.fy, result.cx, result.cy, result.rms_px)
    return result


# -- mosaics, files and capture.yaml ---------------------------------------------------------------


def mosaic_to_superpixel_intensity(mosaic: np.ndarray) -> np.ndarray:
    """(H, W) raw polarisation mosaic -> (H/2, W/2) float64 mean of each 2x2 block (∝ s0).

    Super-pixel (i, j) is centred on raw pixel coordinates (2 j + 0.5, 2 i + 0.5).
    """
    m = np.asarray(mosaic, dtype=np.float64)
    if m.ndim != 2 or m.shape[0] % 2 or m.shape[1] % 2:
        raise ValueError(f"a raw mosaic must have shape (H, W) with even H and W; got {m.shape}")
    return 0.25 * (m[0::2, 0::2] + m[0::2, 1::2] + m[1::2, 0::2] + m[1::2, 1::2])


def _read_image(path: str | Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"cannot read the image {path} (missing file or unsupported format)")
    return image


def _mask_at_raw_size(mask: np.ndarray, raw_hw: tuple[int, int], path: str | Path | None) -> np.ndarray:
    """The (H, W) sphere mask at the images' size: as it is, or upsampled (nearest) from the
    super-pixel size (H/2, W/2) of a capture's mask.png; any other size is an ImageError."""
    h, w = raw_hw
    if mask.shape == (h, w):
        return mask
    if mask.shape == (h // 2, w // 2) and h % 2 == 0 and w % 2 == 0:
        return np.repeat(np.repeat(mask, 2, axis=0), 2, axis=1)  # each super-pixel covers its 2x2 block
    raise ImageError(
        f"sphere mask {path}: {mask.shape[1]}x{mask.shape[0]} pixels; it must be the images' size {w}x{h} or the "
        f"super-pixel size {w // 2}x{h // 2} (half of it, like a capture's mask.png)"
    )


def calibrate_lights_from_files(
    image_paths: Sequence[str | Path],
    *,
    mask_path: str | Path | None = None,
    circle: tuple[float, float, float] | None = None,
    intrinsics: Intrinsics | None = None,
    mosaic: bool = True,
    capture_yaml: str | Path | None = None,
) -> np.ndarray:
    """Light directions from mirror-sphere image files (``polarshape calibrate lights``).

    Args:
        image_paths: one image per light, in light order.
        mask_path: sphere mask image (non-zero = sphere), at the images' resolution or at half of it
            (super-pixels, like a capture's own mask.png: upsampled, nearest); or
        circle: ``(cu, cv, radius)`` in the images' pixels (orthographic).
        intrinsics: None (orthographic) or pinhole intrinsics in the images' (raw) pixels.
        mosaic: images are raw polarisation mosaics: average 2x2 blocks first.
        capture_yaml: if given, write the directions into this capture.yaml (or capture folder).

    Returns:
        (K, 3) unit light directions, camera frame.
    """
    images = [_read_image(p).astype(np.float64) for p in image_paths]
    images = [cv2.cvtColor(i.astype(np.float32), cv2.COLOR_BGR2GRAY).astype(np.float64) if i.ndim == 3 else i
              for i in images]
    mask = None if mask_path is None else _read_image(mask_path)
    if mask is not None and mask.ndim == 3:
        mask = mask[..., 0]
    if mask is not None and images:
        mask = _mask_at_raw_size(mask, images[0].shape[:2], mask_path)
    if mosaic:
        images = [mosaic_to_superpixel_intensity(i) for i in images]
        if mask is not None:
            mask = mosaic_to_superpixel_intensity(mask != 0) >= 0.5
        if circle is not None:
            circle = ((circle[0] - 0.5) / 2, (circle[1] - 0.5) / 2, circle[2] / 2)
        if intrinsics is not None:
            intrinsics = intrinsics.raw_to_superpixel()
    directions = light_directions_from_mirror_sphere(images, mask=mask, circle=circle, intrinsics=intrinsics)
    if capture_yaml is not None:
        update_capture_yaml(capture_yaml, lights=directions)
    return directions


def calibrate_intrinsics_from_files(
    image_paths: Sequence[str | Path],
    board: CharucoBoardSpec = CharucoBoardSpec(),
    *,
    mosaic: bool = True,
    capture_yaml: str | Path | None = None,
) -> Intrinsics:
    """Intrinsics from ChArUco image files (``polarshape calibrate intrinsics``), in raw pixels.

    With ``mosaic`` the raw polarisation mosaics are reduced to super-pixel intensity images,
    calibrated, and the result converted to raw-mosaic pixels. With ``capture_yaml`` the result
    is written into it.
    """
    images = [_read_image(p) for p in image_paths]
    if mosaic:
        images = [mosaic_to_superpixel_intensity(i if i.ndim == 2 else i[..., 0]) for i in images]
    result = calibrate_intrinsics_charuco(images, board)
    if mosaic:
        result = result.superpixel_to_raw()
    if capture_yaml is not None:
        update_capture_yaml(capture_yaml, intrinsics=result)
    return result


def update_capture_yaml(
    path: str | Path,
    *,
    lights: np.ndarray | Sequence[Sequence[float]] | None = None,
    intrinsics: Intrinsics | Mapping[str, float] | None = None,
    distortion: Sequence[float] | None = None,
) -> Path:
    """Write calibration results into a capture.yaml, atomically, keeping everything else.

    Args:
        path: the capture.yaml, or the capture folder holding it.
        lights: (K, 3) light directions (camera frame, to the light), one per ``lights`` entry
            in order; each entry gets ``direction`` (a ``position`` is replaced).
        intrinsics: :class:`Intrinsics` or ``{fx, fy, cx, cy}`` in raw-mosaic pixels; sets
            ``camera.intrinsics`` (and ``camera.distortion`` from an :class:`Intrinsics`) and
            ``camera.projection: perspective``.
        distortion: explicit ``camera.distortion`` (OpenCV order), overriding the above.

    Returns:
        The path of the capture.yaml written.
    """
    dirs = None
    if lights is not None:
        dirs = np.asarray(lights, dtype=np.float64)
        if dirs.ndim != 2 or dirs.shape[1] != 3:
            raise ValueError(f"lights must have shape (K, 3); got {dirs.shape}")
        norms = np.linalg.norm(dirs, axis=1, keepdims=True)
        if not np.all(norms > 0) or not np.all(np.isfinite(dirs)):
            raise ValueError("light directions must be finite and non-zero")
        dirs = dirs / norms

    def edit(doc: dict) -> None:
        if dirs is not None:
            set_light_directions(doc, dirs)
        if intrinsics is not None:
            intr = intrinsics if isinstance(intrinsics, Intrinsics) else Intrinsics.from_mapping(intrinsics)
            doc["camera"]["intrinsics"] = intr.to_capture_dict()
            doc["camera"]["projection"] = "perspective"
            if intr.distortion:
                doc["camera"]["distortion"] = [float(x) for x in intr.distortion]
        if distortion is not None:
            doc["camera"]["distortion"] = [float(x) for x in distortion]

    return edit_capture_yaml(path, edit, check_before=False)
