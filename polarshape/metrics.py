"""Errors against a reference: the angle between normals, error statistics, aligned depth error.

A leaf of the package (torch and numpy only): recovery logs with it, the pipeline's evaluation
stage, the benchmarks and the tests measure with it.
"""

from __future__ import annotations

import math
from typing import Any, overload

import numpy as np
import torch
from torch import Tensor

__all__ = ["PERCENTILES", "angular_error_deg", "angular_error_stats", "depth_rmse_absolute", "depth_rmse_aligned"]

#: Percentiles reported by :func:`angular_error_stats`.
PERCENTILES = (25, 75, 90, 95)


@overload
def angular_error_deg(a: Tensor, b: Tensor, mask: Any = None) -> Tensor: ...
@overload
def angular_error_deg(a: np.ndarray, b: np.ndarray, mask: Any = None) -> np.ndarray: ...


def angular_error_deg(a: Any, b: Any, mask: Any = None) -> Any:
    """Angle between vectors in degrees, via atan2(|a×b|, a·b) (robust near 0° and 180°, spec §3).

    Args:
        a, b: (..., 3) vectors of the same shape (need not be unit); NaN or zero length = missing.
            Torch tensors (any device) or numpy arrays.
        mask: optional (...) bool of the entries to evaluate.

    Returns:
        (...) float64 degrees, NaN where either vector is missing or off ``mask``; a tensor for
        tensor input, else a numpy array.
    """
    as_tensor = isinstance(a, Tensor)
    ta = torch.as_tensor(a).to(torch.float64)
    tb = torch.as_tensor(b).to(device=ta.device, dtype=torch.float64)
    if ta.shape != tb.shape or ta.ndim < 1 or ta.shape[-1] != 3:
        raise ValueError(f"vectors must both be (..., 3) of one shape; got {tuple(ta.shape)} and {tuple(tb.shape)}")
    na, nb = ta.norm(dim=-1), tb.norm(dim=-1)
    ok = torch.isfinite(na) & torch.isfinite(nb) & (na > 1e-6) & (nb > 1e-6)
    if mask is not None:
        ok &= torch.as_tensor(mask, dtype=torch.bool, device=ta.device)
    err = torch.rad2deg(torch.atan2(torch.linalg.cross(ta, tb).norm(dim=-1), (ta * tb).sum(-1)))
    err = torch.where(ok, err, torch.full_like(err, math.nan))
    return err if as_tensor else err.cpu().numpy()


def angular_error_stats(error_deg: np.ndarray, reference_pixels: int | None = None) -> dict[str, float]:
    """Mean, median, RMS, percentiles (:data:`PERCENTILES`) and shares below 5°/10°/20° of an error map.

    Args:
        error_deg: (H, W) errors in degrees, NaN = not evaluated.
        reference_pixels: pixels that should have been evaluated (for ``coverage``).
    """
    e = error_deg[np.isfinite(error_deg)]
    if e.size == 0:
        return {"pixels": 0}
    out: dict[str, float] = {
        "pixels": int(e.size),
        "mean_deg": float(e.mean()),
        "median_deg": float(np.median(e)),
        "rms_deg": float(np.sqrt(np.mean(e**2))),
    }
    for q in PERCENTILES:
        out[f"p{q}_deg"] = float(np.percentile(e, q))
    for t in (5, 10, 20):
        out[f"within_{t}deg"] = float(np.mean(e < t))
    if reference_pixels:
        out["coverage"] = float(e.size / reference_pixels)
    return out


def depth_rmse_aligned(depth: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """RMSE of ``depth`` against ``reference`` after the least-squares scale and offset alignment.

    ``reference ≈ a · depth + b`` over the pixels where both are finite (and ``mask``); the RMSE is in
    the reference's unit, ``relative`` divides it by the reference's depth range there.
    """
    d = np.asarray(depth, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    ok = np.isfinite(d) & np.isfinite(r)
    if mask is not None:
        ok &= np.asarray(mask, dtype=bool)
    if ok.sum() < 3:
        return {"pixels": int(ok.sum())}
    x, y = d[ok], r[ok]
    design = np.stack([x, np.ones_like(x)], axis=1)
    (scale, offset), *_ = np.linalg.lstsq(design, y, rcond=None)
    residual = scale * x + offset - y
    rmse = float(np.sqrt(np.mean(residual**2)))
    span = float(y.max() - y.min())
    return {
        "pixels": int(ok.sum()),
        "rmse": rmse,
        "relative": rmse / span if span > 0 else math.nan,
        "scale": float(scale),
        "offset": float(offset),
        "reference_range": span,
    }


def depth_rmse_absolute(depth: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """RMSE of ``depth`` against ``reference`` as they are (no alignment: the absolute placement counts,
    e.g. a near-field depth estimate), over the pixels where both are finite (and ``mask``);
    ``relative_to_distance`` divides it by the reference's median depth (the camera distance)."""
    d = np.asarray(depth, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    ok = np.isfinite(d) & np.isfinite(r)
    if mask is not None:
        ok &= np.asarray(mask, dtype=bool)
    if not ok.any():
        return {"pixels": 0}
    rmse = float(np.sqrt(np.mean((d[ok] - r[ok]) ** 2)))
    distance = float(np.median(r[ok]))
    return {
        "pixels": int(ok.sum()), "rmse": rmse, "relative_to_distance": rmse / distance if distance > 0 else math.nan,
        "median_error": float(np.median(d[ok]) - distance), "reference_median": distance,
    }
