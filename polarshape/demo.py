"""Forward-model demo (`polarshape demo`): a sphere rendered with the FMBRDF under one light.

Writes intensity (16-bit PNG), DoLP and AoLP (colour-mapped PNG), the raw IMX250MZR mosaic a
polarisation camera would record (16-bit PNG), the Stokes images (NPY) and the parameters (JSON),
atomically into one folder.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from polarshape.brdf import FMBRDFParams, fmbrdf_stokes
from polarshape.imaging.mosaic import MosaicLayout, mosaic_from_stokes
from polarshape.imaging.stokes import aolp, dolp
from polarshape.checks import to_numpy
from polarshape.io.atomic import atomic_directory

logger = logging.getLogger(__name__)


def demo_material() -> FMBRDFParams:
    """FMBRDF parameters of the demo sphere (spec §2)."""
    return FMBRDFParams(ior=1.5, alpha=0.25, beta=2.0, kappa=20.0, k_s=1.0, k_b=0.6)


def sphere_normals(size: int, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Orthographic unit sphere filling a size×size image: normals (H, W, 3) (camera frame, facing
    the camera: n_z < 0) and mask (H, W)."""
    c = (torch.arange(size, dtype=dtype) + 0.5) / size * 2.0 - 1.0
    y, x = torch.meshgrid(c, c, indexing="ij")
    r2 = x * x + y * y
    mask = r2 < 1.0
    z = -torch.sqrt((1.0 - r2).clamp_min(0.0))
    n = torch.stack([x, y, z], dim=-1)
    return torch.where(mask[..., None], n, torch.zeros_like(n)), mask


def render_demo(
    size: int = 256, light_deg: tuple[float, float] = (35.0, -30.0), material: FMBRDFParams | None = None
) -> dict[str, np.ndarray]:
    """Render Stokes (H, W, 3), DoLP, AoLP (H, W), mask (H, W) and the raw mosaic (2H, 2W) of the
    demo sphere (``material`` default: :func:`demo_material`)."""
    material = demo_material() if material is None else material
    normals, mask = sphere_normals(size)
    zen, az = (math.radians(a) for a in light_deg)
    light = torch.tensor([math.sin(zen) * math.cos(az), math.sin(zen) * math.sin(az), -math.cos(zen)])
    view = torch.tensor([0.0, 0.0, -1.0])
    stokes = fmbrdf_stokes(normals, light, view, **material.as_kwargs(), tables=material.build_tables())  # (H, W, 3)
    stokes = stokes * mask[..., None]
    chw = stokes.permute(2, 0, 1)
    mosaic = mosaic_from_stokes(chw, MosaicLayout.imx250mzr())  # (2H, 2W)
    return {
        "stokes": to_numpy(stokes),
        "dolp": to_numpy(dolp(chw) * mask),
        "aolp": to_numpy(aolp(chw) * mask),
        "mask": to_numpy(mask),
        "mosaic": to_numpy(mosaic),
    }


def _colour(values: np.ndarray, mask: np.ndarray, cmap: str, vmin: float, vmax: float) -> np.ndarray:
    from matplotlib import colormaps  # ~0.3 s to import: only when a map is coloured
    rgb = colormaps[cmap]((np.clip(values, vmin, vmax) - vmin) / (vmax - vmin))[..., :3]
    rgb[~mask] = 0.0
    return cv2.cvtColor((rgb * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR)


def run_demo(out: str | Path, *, size: int = 256, overwrite: bool = False) -> dict[str, object]:
    """Render and write the demo folder; returns a summary (paths and figures)."""
    t0 = time.perf_counter()
    material = demo_material()
    r = render_demo(size, material=material)
    elapsed = time.perf_counter() - t0
    s0, mask = r["stokes"][..., 0], r["mask"]
    peak = float(s0.max())
    with atomic_directory(out, overwrite=overwrite) as tmp:
        cv2.imwrite(str(tmp / "intensity.png"), np.round(s0 / peak * 65535).astype(np.uint16))
        cv2.imwrite(str(tmp / "dolp.png"), _colour(r["dolp"], mask, "viridis", 0.0, max(float(r["dolp"].max()), 1e-6)))
        cv2.imwrite(str(tmp / "aolp.png"), _colour(r["aolp"], mask, "twilight", -math.pi / 2, math.pi / 2))
        cv2.imwrite(str(tmp / "mosaic.png"), np.round(r["mosaic"] / peak * 65535).astype(np.uint16))
        np.save(tmp / "stokes.npy", r["stokes"].astype(np.float32))
        summary = {
            "material": material.as_kwargs(),
            "light_zenith_azimuth_deg": [35.0, -30.0],
            "size": size,
            "peak_s0": peak,
            "max_dolp": float(r["dolp"].max()),
            "render_seconds": elapsed,
            "conventions": "camera frame x right, y down, z forward; AoLP from image x toward y (down); "
            "mosaic layout IMX250MZR [[90,135],[45,0]] in our angles",
        }
        (tmp / "demo.json").write_text(json.dumps(summary, indent=2))
    logger.info("demo written to %s in %.2f s", out, elapsed)
    return {"out": str(Path(out).absolute()), **summary}
