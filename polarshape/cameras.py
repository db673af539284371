"""Camera models: orthographic and pinhole perspective, shared by the simulator, recovery and surface.

Camera frame (OpenCV): x right, y down, z forward; pixel (u, v) = (column, row) with pixel centres at
integer coordinates. A camera describes one pixel grid: the raw mosaic (the polariser mosaic's
resolution, what the simulator traces) or, through :meth:`OrthographicCamera.superpixel` /
:meth:`PerspectiveCamera.superpixel`, the grid of 2×2 super-pixels that recovery works on, with each
super-pixel's ray through the point of its block where the Stokes vector is sampled.

Every camera answers the same calls, so call sites never test the projection (pytorch3d's
``cameras.py`` is the model):

- :meth:`rays` — origins and unit directions of every pixel (H, W, 3);
- :meth:`view_directions` — V, surface → camera, for points (..., 3);
- :meth:`pixel_view_directions` — V of every pixel of the grid (H, W, 3), before any depth is known;
- :meth:`unproject` — depth map (H, W) → camera-frame points (H, W, 3);
- :meth:`superpixel` — the same camera at super-pixel resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from polarshape.checks import to_numpy

__all__ = [
    "SAMPLE_SITES", "Camera", "OrthographicCamera", "PerspectiveCamera", "camera_from_spec", "intrinsic_matrix",
    "normalised_coordinates",
]

#: Where in each 2×2 block a super-pixel is sampled: (row, column) of a site, or None = the block centre.
SAMPLE_SITES: dict[str, tuple[int, int] | None] = {
    "centre": None, "top_left": (0, 0), "top_right": (0, 1), "bottom_left": (1, 0), "bottom_right": (1, 1),
}


def _check_size(width: int, height: int, *, even: bool) -> None:
    if width <= 0 or height <= 0 or (even and (width % 2 or height % 2)):
        need = "positive and even (whole 2x2 polariser blocks)" if even else "positive"
        raise ValueError(f"camera width and height must be {need}, got {width}x{height}")


def _pixel_grid(width: int, height: int, device: torch.device | str, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype),
        torch.arange(width, device=device, dtype=dtype),
        indexing="ij",
    )
    return u, v  # (H, W) each


def _site_offset(sample_at: str) -> tuple[float, float]:
    """(dy, dx) raw-pixel offset of a block's sample point from its top-left site."""
    if sample_at not in SAMPLE_SITES:
        raise ValueError(f"sample_at must be one of {tuple(SAMPLE_SITES)}; got {sample_at!r}")
    site = SAMPLE_SITES[sample_at]
    return (0.5, 0.5) if site is None else (float(site[0]), float(site[1]))


def _depth_array(depth: Any) -> np.ndarray:
    z = to_numpy(depth, np.float64)
    if z.ndim != 2:
        raise ValueError(f"depth must have shape (H, W); got {z.shape}")
    return z


def intrinsic_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(3, 3) float64 pinhole intrinsic matrix K (pixels; no skew)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def normalised_coordinates(uv: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                           distortion: tuple[float, ...] | None = None) -> np.ndarray:
    """(..., 2) float64 (x/z, y/z) of the rays through pixel coordinates ``uv`` (..., 2), undistorted
    with the OpenCV model (``cv2.undistortPoints``) when ``distortion`` has a non-zero coefficient."""
    uv = np.asarray(uv, dtype=np.float64)
    if distortion is not None and any(abs(c) > 0 for c in distortion):
        import cv2

        xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), intrinsic_matrix(fx, fy, cx, cy),
                                 np.asarray(distortion, dtype=np.float64))
        return xy.reshape(uv.shape)
    return np.stack([(uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy], -1)


@dataclass(frozen=True)
class OrthographicCamera:
    """Orthographic camera: parallel rays along +z from the plane z = 0.

    Attributes:
        width, height: grid size in pixels.
        pixel_size_m: side of one pixel on the object, metres (or any unit: depth comes out in it).
        cx, cy: principal point in pixels (the pixel whose ray passes through x = y = 0);
            None = the grid centre ((W − 1)/2, (H − 1)/2).
        even: the grid is a raw mosaic (whole 2×2 blocks: even sizes); False for super-pixel grids.
    """

    width: int
    height: int
    pixel_size_m: float = 1.0
    cx: float | None = None
    cy: float | None = None
    even: bool = True

    projection = "orthographic"

    def __post_init__(self) -> None:
        _check_size(self.width, self.height, even=self.even)
        if not (math.isfinite(self.pixel_size_m) and self.pixel_size_m > 0):
            raise ValueError(f"pixel_size_m must be > 0 metres, got {self.pixel_size_m}")

    @property
    def principal_point(self) -> tuple[float, float]:
        cx = (self.width - 1) / 2 if self.cx is None else self.cx
        cy = (self.height - 1) / 2 if self.cy is None else self.cy
        return cx, cy

    def rays(self, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
        """Ray origins and unit directions of every pixel: (H, W, 3) each, camera frame."""
        u, v = _pixel_grid(self.width, self.height, device, dtype)
        cx, cy = self.principal_point
        origins = torch.stack([(u - cx) * self.pixel_size_m, (v - cy) * self.pixel_size_m, torch.zeros_like(u)], -1)
        directions = torch.zeros_like(origins)
        directions[..., 2] = 1.0
        return origins, directions

    def view_directions(self, points: Tensor) -> Tensor:
        """V, the unit direction from surface points to the camera: (..., 3) -> (..., 3) = (0, 0, −1)."""
        view = torch.zeros_like(points)
        view[..., 2] = -1.0
        return view

    def pixel_view_directions(self, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64) -> Tensor:
        """(H, W, 3) V of every pixel (no depth needed): (0, 0, −1)."""
        return self.view_directions(torch.zeros(self.height, self.width, 3, device=device, dtype=dtype))

    def unproject(self, depth: Any) -> np.ndarray:
        """(H, W, 3) float64 camera-frame points of a depth map (H, W) of camera z; NaN stays NaN."""
        z = _depth_array(depth)
        if z.shape != (self.height, self.width):
            raise ValueError(f"depth has shape {z.shape}; this camera's grid is {(self.height, self.width)}")
        vv, uu = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        cx, cy = self.principal_point
        return np.stack([(uu - cx) * self.pixel_size_m, (vv - cy) * self.pixel_size_m, z], axis=-1)

    def superpixel(self, sample_at: str = "centre", pixel_size_m: float | None = None) -> OrthographicCamera:
        """This camera on the grid of 2×2 blocks, each pixel's ray through the block's ``sample_at`` point.

        Args:
            sample_at: a key of :data:`SAMPLE_SITES`.
            pixel_size_m: metres per super-pixel (default twice this camera's pixel size).
        """
        dy, dx = _site_offset(sample_at)
        cx, cy = self.principal_point
        size = 2.0 * self.pixel_size_m if pixel_size_m is None else float(pixel_size_m)
        return OrthographicCamera(self.width // 2, self.height // 2, size, (cx - dx) / 2, (cy - dy) / 2, even=False)


@dataclass(frozen=True)
class PerspectiveCamera:
    """Pinhole camera at the origin (intrinsics in this grid's pixels; optional OpenCV distortion).

    Attributes:
        width, height: grid size in pixels.
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels.
        distortion: OpenCV coefficients (k1, k2, p1, p2[, k3, …]) or None; applied to the ray of
            each pixel (:meth:`pixel_view_directions`), never by resampling an image.
        even: the grid is a raw mosaic (whole 2×2 blocks: even sizes); False for super-pixel grids.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] | None = None
    even: bool = True

    projection = "perspective"

    def __post_init__(self) -> None:
        _check_size(self.width, self.height, even=self.even)
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"intrinsics fx, fy must be > 0 pixels, got fx={self.fx}, fy={self.fy}")

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix K."""
        return intrinsic_matrix(self.fx, self.fy, self.cx, self.cy)

    def rays(self, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
        """Ray origins (all 0) and unit directions normalise(((u−cx)/fx, (v−cy)/fy, 1)): (H, W, 3) each
        (no distortion: the simulator renders an ideal pinhole)."""
        u, v = _pixel_grid(self.width, self.height, device, dtype)
        d = torch.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, torch.ones_like(u)], -1)
        return torch.zeros_like(d), torch.nn.functional.normalize(d, dim=-1)

    def view_directions(self, points: Tensor) -> Tensor:
        """V, the unit direction from surface points to the camera centre: (..., 3) -> (..., 3)."""
        return torch.nn.functional.normalize(-points, dim=-1)

    def pixel_view_directions(self, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64) -> Tensor:
        """(H, W, 3) V = −normalise(ray) of every pixel, through the distortion model when present
        (OpenCV ``undistortPoints``: frames are not resampled, which would mix the polariser channels)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        xy = normalised_coordinates(np.stack([u, v], -1), self.fx, self.fy, self.cx, self.cy, self.distortion)
        ray = torch.from_numpy(np.concatenate([xy, np.ones((self.height, self.width, 1))], -1))
        return (-ray / ray.norm(dim=-1, keepdim=True)).to(device=device, dtype=dtype)

    def unproject(self, depth: Any) -> np.ndarray:
        """(H, W, 3) float64 camera-frame points z · K⁻¹ (u, v, 1) of a depth map (H, W) of camera z
        (the pinhole model; NaN stays NaN)."""
        z = _depth_array(depth)
        if z.shape != (self.height, self.width):
            raise ValueError(f"depth has shape {z.shape}; this camera's grid is {(self.height, self.width)}")
        vv, uu = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        rays = np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ np.linalg.inv(self.matrix).T  # (H, W, 3), r_z = 1
        return z[..., None] * rays

    def superpixel(self, sample_at: str = "centre", pixel_size_m: float | None = None) -> PerspectiveCamera:
        """This camera on the grid of 2×2 blocks: super-pixel (x, y) covers raw columns 2x, 2x+1 and
        rows 2y, 2y+1; its ray passes through the block's ``sample_at`` point (centre: 2x + 0.5).

        Args:
            sample_at: a key of :data:`SAMPLE_SITES`.
            pixel_size_m: ignored (perspective cameras have no pixel size; accepted so every camera
                takes the same call).
        """
        dy, dx = _site_offset(sample_at)
        return replace(self, width=self.width // 2, height=self.height // 2, fx=self.fx / 2, fy=self.fy / 2,
                       cx=(self.cx - dx) / 2, cy=(self.cy - dy) / 2, even=False)


#: Either camera model (the acquisition protocol :class:`polarshape.acquisition.Camera` is another thing).
Camera = OrthographicCamera | PerspectiveCamera


def camera_from_spec(spec: Any, width: int, height: int, *, pixel_size_m: float = 1.0) -> Camera:
    """The raw-mosaic camera of a capture's ``camera`` section (:class:`polarshape.io.capture.CameraSpec`).

    Args:
        spec: the camera spec (``projection``, ``intrinsics`` in raw pixels, ``distortion``).
        width, height: raw frame size in pixels.
        pixel_size_m: metres per raw pixel (orthographic only).
    """
    if spec.projection == "orthographic":
        return OrthographicCamera(width, height, pixel_size_m)
    k = spec.intrinsics
    if k is None:
        raise ValueError("capture.yaml: camera.intrinsics are required for a perspective camera")
    distortion = tuple(float(c) for c in spec.distortion) if spec.distortion is not None else None
    return PerspectiveCamera(width, height, k.fx, k.fy, k.cx, k.cy, distortion)
