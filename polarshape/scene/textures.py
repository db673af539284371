"""Albedo textures: a per-point multiplier of a material's diffuse/body albedo (k_b or k_d).

A texture is a pattern p(u, v) ∈ [0, 1] (checker, stripes, or a grey image) mapped onto the
surface, turned into the multiplier ``low + (high − low) · p``. Surface points map to (u, v) by

* ``spherical``: ω = normalise(point − center) in the camera frame,
  u = ½ + atan2(ω_x, −ω_z) / 2π (u = ½ faces the camera), v = atan2(‖(ω_x, ω_z)‖, −ω_y) / π
  (v = 0 at the top of the image, 1 at the bottom);
* ``planar``: projection along the camera's z axis, u = ½ + (x − center_x) / size_m,
  v = ½ + (y − center_y) / size_m.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch
from torch import Tensor

TextureKind = Literal["checker", "stripes", "image"]
TextureMapping = Literal["spherical", "planar"]


def load_grey_image(path: str | Path) -> np.ndarray:
    """A texture image as (H, W) float64 in [0, 1] (colour images are converted to grey).

    Raises ValueError naming the file when it cannot be read.
    """
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"cannot read texture image {path}; give a PNG/JPEG/TIFF file that exists")
    scale = float(np.iinfo(image.dtype).max) if np.issubdtype(image.dtype, np.integer) else 1.0
    image = image.astype(np.float64) / scale
    if image.ndim == 3:
        # OpenCV channel order is B, G, R(, A); Rec. 601 luma weights
        image = image[..., :3] @ np.array([0.114, 0.587, 0.299]) if image.shape[2] >= 3 else image[..., 0]
    return np.clip(image, 0.0, 1.0)


@dataclass(frozen=True)
class AlbedoTexture:
    """A multiplier map on a surface.

    Attributes:
        kind: ``checker`` / ``stripes`` (along u) / ``image``.
        mapping: ``spherical`` or ``planar`` (see the module docstring).
        center: (x, y, z) metres, the mapping's origin (the object's centre).
        cells: pattern cells per unit of u (and v) for checker/stripes.
        low, high: multiplier where the pattern is 0 and 1.
        size_m: planar mapping: metres spanned by u, v ∈ [0, 1].
        image: (H, W) grey values in [0, 1] for ``image`` (row 0 at v = 0).
    """

    kind: TextureKind
    mapping: TextureMapping
    center: tuple[float, float, float]
    cells: float = 8.0
    low: float = 0.25
    high: float = 1.0
    size_m: float = 0.02
    image: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("checker", "stripes", "image"):
            raise ValueError(f"texture kind must be checker, stripes or image, got {self.kind!r}")
        if self.mapping not in ("spherical", "planar"):
            raise ValueError(f"texture mapping must be spherical or planar, got {self.mapping!r}")
        if self.kind == "image" and (self.image is None or self.image.ndim != 2):
            raise ValueError("an image texture needs a (H, W) grey image (set texture.path)")
        if not self.cells > 0 or not self.size_m > 0:
            raise ValueError(f"texture cells and size_m must be > 0, got cells={self.cells}, size_m={self.size_m}")

    def uv(self, points: Tensor) -> Tensor:
        """(N, 3) surface points (metres, camera frame) -> (N, 2) texture coordinates (u, v)."""
        rel = points - torch.tensor(self.center, dtype=points.dtype, device=points.device)  # (N, 3)
        if self.mapping == "planar":
            return 0.5 + rel[:, :2] / self.size_m
        x, y, z = rel.unbind(-1)
        u = 0.5 + torch.atan2(x, -z) / (2 * math.pi)
        v = torch.atan2(torch.sqrt(x * x + z * z), -y) / math.pi
        return torch.stack([u, v], -1)

    def pattern(self, uv: Tensor) -> Tensor:
        """(N, 2) texture coordinates -> (N,) pattern values in [0, 1]."""
        if self.kind == "checker":
            cell = torch.floor(uv * self.cells).to(torch.int64)
            return ((cell[:, 0] + cell[:, 1]) % 2).to(uv.dtype)
        if self.kind == "stripes":
            return (torch.floor(uv[:, 0] * self.cells).to(torch.int64) % 2).to(uv.dtype)
        assert self.image is not None
        u = torch.remainder(uv[:, 0], 1.0) if self.mapping == "spherical" else uv[:, 0].clamp(0.0, 1.0)
        v = uv[:, 1].clamp(0.0, 1.0)
        grid = torch.stack([2 * u - 1, 2 * v - 1], -1)[None, None]  # (1, 1, N, 2), x = u, y = v
        img = torch.as_tensor(self.image, dtype=uv.dtype, device=uv.device)[None, None]  # (1, 1, H, W)
        return torch.nn.functional.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)[0, 0, 0]

    def __call__(self, points: Tensor) -> Tensor:
        """(N, 3) surface points -> (N,) albedo multipliers ``low + (high − low) · pattern``."""
        return self.low + (self.high - self.low) * self.pattern(self.uv(points))


def make_texture(
    kind: TextureKind,
    mapping: TextureMapping,
    center: Sequence[float],
    *,
    cells: float = 8.0,
    low: float = 0.25,
    high: float = 1.0,
    size_m: float = 0.02,
    path: str | Path | None = None,
) -> AlbedoTexture:
    """Build an :class:`AlbedoTexture`, reading ``path`` for ``kind='image'``."""
    image = None
    if kind == "image":
        if path is None:
            raise ValueError("texture kind 'image' needs texture.path (a grey or colour image file)")
        image = load_grey_image(path)
    return AlbedoTexture(kind, mapping, tuple(float(c) for c in center), cells, low, high, size_m, image)  # type: ignore[arg-type]
