"""Per-channel body albedo of a colour polarisation capture, given the normals and the material.

A colour capture (``camera.mosaic.bayer``; :class:`polarshape.recover.observations.ColourInputs`)
is recovered with **shared normals and one material**: normals, (μ, α, β, κ) and k_s come from the
channel mean (:func:`polarshape.recover.preprocess.colour_superpixel_stokes`), as for a mono
capture; then, with white lights, channel c's observations are

    s_c[p, k] = k_s · A[p, k] + k_b,c[p] · B[p, k]

with the same surface part A and body part B in every channel
(:func:`polarshape.recover.reflectometry.render_parts`, spec §8): each channel's k_b is the
closed-form weighted least squares of :func:`polarshape.recover.reflectometry.solve_albedos` with k_s
held (one linear unknown per pixel and channel; no search). The Lambertian model is the same with
A = 0 and B = E (N·L)₊ (the PS albedo ρ, I = ρ E (N·L)₊). By linearity the mean of the three
albedos is the mono fit's k_b wherever the channels' observations are the combined ones.

Pixels with fewer than :data:`polarshape.recover.priors.MIN_OBSERVATIONS` usable observations of a
channel (dark in that colour, or the combined observation invalid), and the pixels whose normal was
filled, take that channel's albedo from their neighbours
(:func:`polarshape.recover.priors.fill_unsupported`), as the mono albedo does.

Example:
    >>> rgb = colour_albedo(inputs, result.normals, "fmbrdf", FMBRDFParams(**fitted))  # doctest: +SKIP
    >>> rgb.shape                                                                         # doctest: +SKIP
    torch.Size([H, W, 3])
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from polarshape.brdf.baselines import lambertian_stokes
from polarshape.brdf.fmbrdf import build_tables
from polarshape.brdf.params import FMBRDFParams
from polarshape.checks import check_shape, to_numpy
from polarshape.imaging.colour import COLOUR_NAMES
from polarshape.recover.observations import Observations, RecoveryInputs, flatten_observations
from polarshape.recover.priors import MIN_OBSERVATIONS, fill_unsupported
from polarshape.recover.reflectometry import render_parts, solve_albedos

logger = logging.getLogger(__name__)

__all__ = ["colour_albedo", "colour_albedo_summary"]


def _unit_parts(model: str, params: FMBRDFParams | None, normals: Tensor, obs: Observations) -> tuple[Tensor, Tensor]:
    """(surface, body) Stokes (P, K, 3) for k_s = k_b = 1 (Lambertian: no surface part, ρ = 1)."""
    if model == "fmbrdf":
        assert params is not None
        tables = build_tables(ior=params.ior, alpha=params.alpha, beta=params.beta, kappa=params.kappa,
                              device=normals.device)
        return render_parts(tables, normals, obs)
    n = normals.unsqueeze(1)  # (P, 1, 3)
    body = lambertian_stokes(n, obs.lights, obs.view.unsqueeze(1), k_d=math.pi)  # (P, K, 3): I = E (N·L)₊
    body = body * obs.irradiance.unsqueeze(-1).to(body.dtype)
    return torch.zeros_like(body), body


def colour_albedo(
    inputs: RecoveryInputs, normals: Tensor, model: str, params: FMBRDFParams | None = None, *,
    per_pixel: bool = True, filled: Tensor | None = None,
) -> Tensor:
    """Body albedo per colour channel (R, G, B) of a colour capture, for known normals and material.

    Args:
        inputs: preprocessed inputs of a colour capture (``inputs.colour`` set), on the grid of ``normals``.
        normals: (H, W, 3) unit normals, camera frame (NaN outside the mask).
        model: ``"fmbrdf"`` (k_b per channel; ``params`` needed, its k_s held) or ``"lambertian"``
            (the PS albedo ρ per channel).
        params: the fitted FMBRDF material (ior, alpha, beta, kappa, k_s).
        per_pixel: one albedo per pixel and channel (else one per channel, as ``recovery.per_pixel_albedo``).
        filled: (H, W) bool pixels whose normal is not their own (they take their neighbours' albedo).

    Returns:
        (H, W, 3) albedo per channel, dtype of ``inputs.stokes``, NaN outside ``inputs.mask``; the
        same units as the mono albedo (their mean is it).

    Raises:
        ValueError: a mono capture, an unknown model, or FMBRDF without ``params``.
    """
    colour = inputs.colour
    if colour is None:
        raise ValueError("colour_albedo needs a colour capture's inputs (camera.mosaic.bayer set; inputs.colour is None)")
    if model not in ("fmbrdf", "lambertian"):
        raise ValueError(f"model must be 'fmbrdf' or 'lambertian'; got {model!r}")
    if model == "fmbrdf" and params is None:
        raise ValueError("colour_albedo with model 'fmbrdf' needs the fitted params (their k_s is held)")
    h, w = inputs.shape
    check_shape(normals, [str(h), str(w), "3"], "normals")
    mask = inputs.mask
    pixels = mask & torch.isfinite(normals).all(-1)  # (H, W)
    out = torch.full((h, w, 3), math.nan, dtype=inputs.stokes.dtype, device=inputs.stokes.device)
    if not bool(pixels.any()):
        return out
    n = normals[pixels].to(inputs.stokes.dtype)  # (P, 3)
    with torch.no_grad():
        surf, body = _unit_parts(model, params, n, flatten_observations(inputs, pixels))  # (P, K, 3) each
        k_s = surf.new_tensor(params.k_s if model == "fmbrdf" else 0.0)
        own = pixels if filled is None else pixels & ~filled
        for c, name in enumerate(COLOUR_NAMES):
            channel = replace(inputs, stokes=colour.stokes[:, c], valid=colour.valid[:, c], colour=None)
            obs = flatten_observations(channel, pixels)
            _, k_b = solve_albedos(surf, body, obs, per_pixel=per_pixel, polarised=inputs.has_polarisation, k_s=k_s)
            albedo = torch.full((h, w), math.nan, dtype=out.dtype, device=out.device)
            albedo[pixels] = k_b.to(out.dtype)
            supported = own & (colour.valid[:, c].sum(0) >= MIN_OBSERVATIONS)
            if per_pixel and bool((pixels & ~supported).any()):
                _, albedo, _ = fill_unsupported(normals, albedo, pixels, supported)
                logger.debug("colour: %s albedo of %d pixels from their neighbours", name, int((pixels & ~supported).sum()))
            out[..., c] = torch.where(mask, albedo, out[..., c])
    return out


def colour_albedo_summary(albedo_rgb: Tensor | np.ndarray, mask: Tensor | np.ndarray) -> dict[str, Any]:
    """params.json's per-channel statistics of an (H, W, 3) albedo over the (H, W) mask.

    Returns:
        ``{"channels": ["R", "G", "B"], "median": [...], "mean": [...], "p05": [...], "p95": [...],
        "chromaticity": [...]}``: the per-channel median, mean and 5/95th percentiles of the finite
        values, and the medians divided by their mean (the colour without the albedo's scale, which
        the irradiance units set).
    """
    values = to_numpy(albedo_rgb, np.float64)[to_numpy(mask, bool)]  # (N, 3)
    stats: dict[str, Any] = {"channels": list(COLOUR_NAMES)}
    for key, fn in (("median", np.nanmedian), ("mean", np.nanmean),
                    ("p05", lambda v, axis: np.nanpercentile(v, 5, axis=axis)),
                    ("p95", lambda v, axis: np.nanpercentile(v, 95, axis=axis))):
        if values.size and np.isfinite(values).any(0).all():
            stats[key] = [float(x) for x in fn(values, axis=0)]
        else:
            stats[key] = [None, None, None]
    med = stats["median"]
    total = sum(med) if None not in med else 0.0
    stats["chromaticity"] = [3.0 * x / total for x in med] if total > 0 else [None, None, None]
    return stats
