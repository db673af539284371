"""Camera models of the simulator: one ray per raw-mosaic pixel.

Camera frame (OpenCV): x right, y down, z forward; pixel (u, v) = (column, row) with pixel centres
at integer coordinates. Sizes are in raw-mosaic pixels (the polariser mosaic's resolution), so a
2×2 super-pixel is four rays that meet four different surface points, as on a real sensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


def _check_size(width: int, height: int) -> None:
    if width <= 0 or height <= 0 or width % 2 or height % 2:
        raise ValueError(
            f"camera width and height must be positive and even (whole 2x2 polariser blocks), got {width}x{height}"
        )


def _pixel_grid(width: int, height: int, device: torch.device | str, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype),
        torch.arange(width, device=device, dtype=dtype),
        indexing="ij",
    )
    return u, v  # (H, W) each


@dataclass(frozen=True)
class OrthographicCamera:
    """Orthographic camera: parallel rays along +z from the plane z = 0.

    Attributes:
        width, height: raw-mosaic size in pixels (even).
        pixel_size_m: side of one raw pixel on the object, metres.
        cx, cy: principal point in pixels (the pixel whose ray passes through x = y = 0);
            None = the image centre ((W − 1)/2, (H − 1)/2).
    """

    width: int
    height: int
    pixel_size_m: float
    cx: float | None = None
    cy: float | None = None

    projection = "orthographic"

    def __post_init__(self) -> None:
        _check_size(self.width, self.height)
        if not self.pixel_size_m > 0:
            raise ValueError(f"pixel_size_m must be > 0 metres, got {self.pixel_size_m}")

    @property
    def principal_point(self) -> tuple[float, float]:
        cx = (self.width - 1) / 2 if self.cx is None else self.cx
        cy = (self.height - 1) / 2 if self.cy is None else self.cy
        return cx, cy

    def rays(self, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
        """Ray origins and unit directions of every pixel: (H, W, 3) each, metres, camera frame."""
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


@dataclass(frozen=True)
class PerspectiveCamera:
    """Pinhole camera at the origin with intrinsics in raw-mosaic pixels (no distortion).

    Attributes:
        width, height: raw-mosaic size in pixels (even).
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    projection = "perspective"

    def __post_init__(self) -> None:
        _check_size(self.width, self.height)
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"intrinsics fx, fy must be > 0 pixels, got fx={self.fx}, fy={self.fy}")

    def rays(self, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
        """Ray origins (all 0) and unit directions normalise(((u−cx)/fx, (v−cy)/fy, 1)):
        (H, W, 3) each."""
        u, v = _pixel_grid(self.width, self.height, device, dtype)
        d = torch.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, torch.ones_like(u)], -1)
        return torch.zeros_like(d), torch.nn.functional.normalize(d, dim=-1)

    def view_directions(self, points: Tensor) -> Tensor:
        """V, the unit direction from surface points to the camera centre: (..., 3) -> (..., 3)."""
        return torch.nn.functional.normalize(-points, dim=-1)

    def intrinsics(self) -> dict[str, float]:
        """{fx, fy, cx, cy} as written to capture.yaml."""
        return {"fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy)}


#: Either camera model (the acquisition protocol `polarshape.acquisition.Camera` is another thing).
CameraModel = OrthographicCamera | PerspectiveCamera
