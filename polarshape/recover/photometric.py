"""Lambertian photometric stereo: plain least squares and a robust variant (shadows, highlights).

Model (spec §10, Lambertian baseline) for pixel p under light k:

    I[k, p] = albedo[p] * E[k, p] * max(0, N[p] · L[k, p])

with ``E`` the relative light intensity (per light, or per pixel for point lights, where it also
carries the 1/r² fall-off) and ``albedo`` the scaled diffuse reflectance (``k_d / π`` of spec §10,
times exposure). Frames: camera frame (OpenCV: x right, y down, z forward into the scene), ``L`` the
unit direction from the surface point to the light, ``V`` the unit direction from the surface point
to the camera (orthographic default ``V = (0, 0, -1)``); a visible surface has ``N · V > 0``.

Solving: per pixel, ``b = albedo * N`` minimises ``Σ_k w_k (I_k - E_k L_k · b)²`` (weights ``w`` are
1 for used observations, 0 otherwise). All pixels are solved at once through the 3×3 normal
equations ``A b = r`` with ``A = Σ w E² L Lᵀ`` (closed-form symmetric inverse, batched);
pixels whose ``A`` is (nearly) singular get the minimum-norm solution from a batched eigen
decomposition instead. Then ``albedo = |b|`` (≥ 0) and ``N = b / |b|``.

**Flip rule.** A least-squares ``b`` that points away from the camera (``b · V < 0``; this happens
at grazing pixels with noise, or with inconsistent data) is mirrored across the plane
perpendicular to ``V``: ``N ← N − 2 (N · V) V`` (orthographic: ``n_z ← −n_z``). This keeps the
normal's image-plane azimuth and its angle to the image plane, and makes ``N · V ≥ 0``.
Pixels with ``b = 0`` (no usable light) get ``N = V`` and ``albedo = 0``.

Example::

    >>> lights = torch.tensor([[0.5, 0.0, -0.866], [0.0, 0.5, -0.866], [-0.5, -0.5, -0.707]])
    >>> normals, albedo = lambertian_ps(images, lights / lights.norm(dim=-1, keepdim=True))
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass

import torch
from torch import Tensor

logger = logging.getLogger(__name__)

__all__ = [
    "PSReason",
    "RobustPSResult",
    "lambertian_ps",
    "robust_lambertian_ps",
]

#: Lights must be unit vectors to this tolerance on |L| (relative).
_UNIT_TOLERANCE = 1e-3


class PSReason(enum.IntEnum):
    """Per-pixel outcome code of :func:`robust_lambertian_ps` (0 = valid)."""

    OK = 0
    #: Pixel excluded by the caller's pixel mask.
    MASKED = 1
    #: Fewer than 3 usable observations after removing dark, saturated, non-finite and specular ones.
    TOO_FEW_LIGHTS = 2
    #: The usable lights are (nearly) coplanar: condition number of the weighted light matrix
    #: above ``max_condition``.
    ILL_CONDITIONED = 3
    #: The least-squares solution pointed away from the camera (b · V < 0): data inconsistent with
    #: a visible Lambertian surface; the normal was mirrored by the flip rule.
    BACK_FACING = 4
    #: After trimming, a used observation still deviates from the fit by more than the outlier
    #: threshold (a highlight spread over too many lights to isolate, or non-Lambertian data).
    INCONSISTENT = 5


@dataclass(frozen=True)
class RobustPSResult:
    """Output of :func:`robust_lambertian_ps`; ``S`` is the spatial shape of the input.

    Attributes:
        normals: (*S, 3) unit normals, camera frame, facing the camera (flip rule in the module doc).
        albedo: (*S,) ≥ 0, in the units of ``intensity / light_intensity``.
        valid: (*S,) bool, ``reason == PSReason.OK``.
        reason: (*S,) int64 :class:`PSReason` codes.
        used: (K, *S) bool, the observations the final fit used.
        n_used: (*S,) int64, number of used observations.
        condition: (*S,) condition number σ_max/σ_min of the used, intensity-weighted light matrix
            (``inf`` when fewer than 3 observations).
    """

    normals: Tensor
    albedo: Tensor
    valid: Tensor
    reason: Tensor
    used: Tensor
    n_used: Tensor
    condition: Tensor


# --------------------------------------------------------------------------------------------
# Input handling
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Flat:
    """Inputs flattened to P pixels."""

    intensity: Tensor  # (K, P)
    lights: Tensor  # (K, 3) shared, or (K, P, 3) per pixel
    light_intensity: Tensor  # (K, 1) or (K, P)
    pixel_mask: Tensor  # (P,) bool
    obs_mask: Tensor  # (K, P) bool: finite, not masked, E > 0
    view: Tensor  # (1, 3) or (P, 3)
    spatial: tuple[int, ...]


def _prepare(
    intensity: Tensor,
    lights: Tensor,
    light_intensity: Tensor | None,
    mask: Tensor | None,
    view_dirs: Tensor | None,
) -> _Flat:
    """Check every input and flatten it to P pixels; shapes as in :class:`_Flat`."""
    if not isinstance(intensity, Tensor) or not isinstance(lights, Tensor):
        raise TypeError("intensity and lights must be torch.Tensor objects")
    # Shape errors are raised in argument order: intensity, lights, light_intensity, mask, view.
    flat_i, spatial = _flatten_intensity(intensity)  # (K, P)
    k = flat_i.shape[0]
    dtype, device = flat_i.dtype, flat_i.device
    flat_lights = _flatten_lights(lights, k, spatial, dtype, device)
    flat_e = _flatten_light_intensity(light_intensity, k, spatial, dtype, device)
    pixel_mask, obs_mask = _flatten_masks(mask, torch.isfinite(flat_i) & (flat_e > 0), spatial)
    # Non-finite observations are never used; zero them so that no NaN leaks into sums.
    flat_i = torch.where(obs_mask, flat_i, torch.zeros((), dtype=dtype, device=device))
    view = _flatten_view_dirs(view_dirs, spatial, dtype, device)
    return _Flat(flat_i, flat_lights, flat_e, pixel_mask, obs_mask, view, spatial)


def _flatten_intensity(intensity: Tensor) -> tuple[Tensor, tuple[int, ...]]:
    """Check a (K, *S) floating-point intensity; return it as (K, P) and the spatial shape S."""
    if not intensity.is_floating_point():
        raise ValueError(f"intensity must be a floating-point tensor; got dtype {intensity.dtype}")
    if intensity.ndim < 2:
        raise ValueError(
            "intensity must have shape (K, P) or (K, H, W) (K lights first); "
            f"got shape {tuple(intensity.shape)}"
        )
    k = intensity.shape[0]
    spatial = tuple(intensity.shape[1:])
    p = math.prod(spatial)
    if k < 1 or p < 1:
        raise ValueError(
            f"intensity must hold at least one light and one pixel; got shape {tuple(intensity.shape)}"
        )
    return intensity.reshape(k, p), spatial


def _unbroadcast(x: Tensor, start: int, ndim: int) -> Tensor:
    """``x`` without its axes ``start … start + ndim − 1`` when they are a zero-stride broadcast.

    Directional lights reach here as (K, H, W, 3) views of (K, 3) (``Lights.illuminate`` expands
    them without copying); fitting them as shared lights is exact and turns the per-pixel sums into
    matrix products.
    """
    if ndim > 0 and x.dim() >= start + ndim and all(x.stride(d) == 0 for d in range(start, start + ndim)):
        return x[(slice(None),) * start + (0,) * ndim]
    return x


def _flatten_lights(
    lights: Tensor, k: int, spatial: tuple[int, ...], dtype: torch.dtype, device: torch.device
) -> Tensor:
    """Check unit, finite lights (K, 3) or (K, *S, 3); return (K, 3) (shared, also when (K, *S, 3)
    is a broadcast of them) or (K, P, 3) in ``dtype``."""
    if lights.shape == (k, *spatial, 3):
        lights = _unbroadcast(lights, 1, len(spatial))
    lights = lights.to(device=device, dtype=dtype)
    if lights.shape == (k, 3):
        flat_lights = lights
    elif lights.shape == (k, *spatial, 3):
        flat_lights = lights.reshape(k, math.prod(spatial), 3)
    else:
        raise ValueError(
            f"lights must have shape (K, 3) = ({k}, 3) for directional lights or (K, *S, 3) = "
            f"{(k, *spatial, 3)} for per-pixel (point-light) directions; got {tuple(lights.shape)}"
        )
    if not bool(torch.isfinite(flat_lights).all()):
        raise ValueError("lights contain NaN or Inf; check the light calibration")
    norms = flat_lights.norm(dim=-1)
    if bool(((norms - 1.0).abs() > _UNIT_TOLERANCE).any()):
        raise ValueError(
            "lights must be unit direction vectors (surface → light); got norms in "
            f"[{float(norms.min()):.4g}, {float(norms.max()):.4g}]. Normalise them and put any "
            "intensity or 1/r² fall-off into light_intensity"
        )
    return flat_lights


def _flatten_light_intensity(
    light_intensity: Tensor | None,
    k: int,
    spatial: tuple[int, ...],
    dtype: torch.dtype,
    device: torch.device,
) -> Tensor:
    """Check E ≥ 0, None / (K,) / (K, *S); return (K, 1) (shared, default 1) or (K, P)."""
    if light_intensity is None:
        return torch.ones(k, 1, dtype=dtype, device=device)
    if isinstance(light_intensity, Tensor) and light_intensity.shape == (k, *spatial):
        light_intensity = _unbroadcast(light_intensity, 1, len(spatial))
    light_intensity = torch.as_tensor(light_intensity, dtype=dtype, device=device)
    if light_intensity.shape == (k,):
        flat_e = light_intensity.reshape(k, 1)
    elif light_intensity.shape == (k, *spatial):
        flat_e = light_intensity.reshape(k, math.prod(spatial))
    else:
        raise ValueError(
            f"light_intensity must have shape (K,) = ({k},) or (K, *S) = {(k, *spatial)}; "
            f"got {tuple(light_intensity.shape)}"
        )
    if not bool(torch.isfinite(flat_e).all()) or bool((flat_e < 0).any()):
        raise ValueError("light_intensity must be finite and ≥ 0 (0 disables a light)")
    return flat_e


def _flatten_masks(
    mask: Tensor | None, obs_mask: Tensor, spatial: tuple[int, ...]
) -> tuple[Tensor, Tensor]:
    """Merge the caller's (*S,) pixel or (K, *S) observation mask into ``obs_mask`` (K, P).

    Returns the pixel mask (P,) (all True unless a pixel mask was given) and the observation mask
    (K, P), False wherever the pixel is masked.
    """
    k, p = obs_mask.shape
    pixel_mask = torch.ones(p, dtype=torch.bool, device=obs_mask.device)
    if mask is not None:
        if not isinstance(mask, Tensor):
            raise TypeError("mask must be a torch.Tensor (bool) or None")
        mask = mask.to(device=obs_mask.device).bool()
        if mask.shape == spatial:
            pixel_mask = mask.reshape(p)
        elif mask.shape == (k, *spatial):
            obs_mask = obs_mask & mask.reshape(k, p)
        else:
            raise ValueError(
                f"mask must have the pixel shape {spatial} or the observation shape {(k, *spatial)}; "
                f"got {tuple(mask.shape)}"
            )
    return pixel_mask, obs_mask & pixel_mask.unsqueeze(0)


def _flatten_view_dirs(
    view_dirs: Tensor | None, spatial: tuple[int, ...], dtype: torch.dtype, device: torch.device
) -> Tensor:
    """Check unit view directions None / (3,) / (*S, 3); return (1, 3) (default (0, 0, -1)) or (P, 3)."""
    if view_dirs is None:
        return torch.tensor([[0.0, 0.0, -1.0]], dtype=dtype, device=device)
    if view_dirs.shape == (*spatial, 3):
        view_dirs = _unbroadcast(view_dirs, 0, len(spatial))
    view_dirs = view_dirs.to(device=device, dtype=dtype)
    if view_dirs.shape == (3,):
        view = view_dirs.reshape(1, 3)
    elif view_dirs.shape == (*spatial, 3):
        view = view_dirs.reshape(math.prod(spatial), 3)
    else:
        raise ValueError(
            f"view_dirs must have shape (3,) or (*S, 3) = {(*spatial, 3)} (unit, surface → "
            f"camera); got {tuple(view_dirs.shape)}"
        )
    vn = view.norm(dim=-1)
    if _any_true(~torch.isfinite(view)) or _any_true((vn - 1.0).abs() > _UNIT_TOLERANCE):
        raise ValueError("view_dirs must be finite unit vectors (surface → camera)")
    return view


def _check_light_geometry(flat: _Flat, max_condition: float, allow_degenerate: bool) -> bool:
    """Raise (or, with ``allow_degenerate``, report) a degenerate light set: K < 3 or coplanar.

    Returns True when the full light set is degenerate (only possible with allow_degenerate).
    """
    k = flat.intensity.shape[0]
    hint = " (pass allow_degenerate=True for a minimum-norm answer flagged invalid)"
    if k < 3:
        if allow_degenerate:
            logger.warning("photometric stereo with %d light(s): returning a degenerate answer", k)
            return True
        raise ValueError(
            f"lights: got {k} light(s); Lambertian photometric stereo needs at least 3 lights "
            f"whose directions are not coplanar{hint}"
        )
    if flat.lights.ndim == 2:
        if flat.light_intensity.shape[1] == 1:
            weighted = flat.lights * flat.light_intensity  # (K, 3) with E (K, 1) shared
            cond = _condition_from_gram(weighted.T @ weighted)
            bad = bool(cond > max_condition)
            worst = float(cond)
        else:
            gram = torch.einsum("kp,ki,kj->pij", flat.light_intensity**2, flat.lights, flat.lights)
            cond = _condition_from_gram(gram)[flat.pixel_mask]
            bad = bool((cond > max_condition).any()) if cond.numel() else False
            worst = float(cond.max()) if cond.numel() else 0.0
    else:
        gram = torch.einsum(
            "kp,kpi,kpj->pij", flat.light_intensity.expand(k, -1) ** 2, flat.lights, flat.lights
        )
        cond = _condition_from_gram(gram)[flat.pixel_mask]
        bad = bool((cond > max_condition).any()) if cond.numel() else False
        worst = float(cond.max()) if cond.numel() else 0.0
    if bad:
        if allow_degenerate:
            logger.warning("lights nearly coplanar (condition %.3g): returning a degenerate answer", worst)
            return True
        raise ValueError(
            f"lights: the {k} light directions are (nearly) coplanar — condition number "
            f"{worst:.3g} of the intensity-weighted light matrix exceeds max_condition="
            f"{max_condition:g}; add a light out of their plane{hint}"
        )
    return False


# --------------------------------------------------------------------------------------------
# Masks: torch's bool reductions and conversions are many times slower on the CPU than the same
# on a uint8 view (measured at 9 × 32768: any(0) 0.42 ms against 0.006 ms; sum(0) into int64 0.26 ms
# against 0.02 ms; .to(float32) 0.19 ms against 0.045 ms); the results are the same.
# --------------------------------------------------------------------------------------------


def _any_true(mask: Tensor) -> bool:
    """``bool(mask.any())`` of a bool tensor."""
    return mask.numel() > 0 and bool(mask.view(torch.uint8).amax())


def _any_along(mask: Tensor, dim: int) -> Tensor:
    """``mask.any(dim)`` of a bool tensor with a non-empty ``dim``."""
    return mask.view(torch.uint8).amax(dim) != 0


def _count(mask: Tensor, dim: int) -> Tensor:
    """``mask.sum(dim)`` (int64) of a bool tensor whose ``dim`` is shorter than 2¹⁵ (the lights)."""
    return mask.view(torch.uint8).sum(dim, dtype=torch.int16).to(torch.int64)


def _weights(mask: Tensor, dtype: torch.dtype) -> Tensor:
    """``mask.to(dtype)``: 1 where True, 0 elsewhere."""
    return mask.view(torch.uint8).to(dtype)


# --------------------------------------------------------------------------------------------
# Batched weighted least squares
# --------------------------------------------------------------------------------------------


def _sym3_entries(a: Tensor) -> Tensor:
    """(6, ...) the entries a00, a11, a22, a01, a02, a12 of symmetric 3×3 matrices (..., 3, 3), each a
    contiguous (...) block (elementwise work on them is then vectorised, not strided)."""
    order = torch.tensor([0, 4, 8, 1, 2, 5], device=a.device)
    return a.reshape(-1, 9).T.index_select(0, order).reshape(6, *a.shape[:-2])


def _sym3_extreme_eigenvalues(a: Tensor) -> tuple[Tensor, Tensor]:
    """Smallest and largest eigenvalues (...,) of symmetric 3×3 matrices (..., 3, 3), in float64.

    The closed form of the characteristic cubic (trigonometric solution; Smith, CACM 4(4), 1961),
    written here because ``torch.linalg.eigvalsh`` on millions of 3×3 matrices was the largest cost
    of robust PS (0.42 of 1.58 s at 128²); in float64 the smallest eigenvalue of a unit-trace matrix
    is exact to ~1e-15, far below the condition limits used here (cond(A) ≤ 1e6).
    """
    a00, a11, a22, a01, a02, a12 = _sym3_entries(a).to(torch.float64)
    q = (a00 + a11 + a22) / 3.0
    off = a01 * a01 + a02 * a02 + a12 * a12
    d0, d1, d2 = a00 - q, a11 - q, a22 - q
    p = torch.sqrt(((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * off) / 6.0).clamp_min(0.0))
    safe_p = torch.where(p > 0, p, torch.ones_like(p))
    # det((A − qI) / p) / 2 = cos 3φ
    det_b = (d0 * (d1 * d2 - a12 * a12) - a01 * (a01 * d2 - a12 * a02) + a02 * (a01 * a12 - d1 * a02)) / safe_p**3
    phi = torch.acos((0.5 * det_b).clamp(-1.0, 1.0)) / 3.0
    hi = torch.where(p > 0, q + 2.0 * p * torch.cos(phi), q)
    lo = torch.where(p > 0, q + 2.0 * p * torch.cos(phi + 2.0 * math.pi / 3.0), q)
    return lo, hi


def _condition_from_gram(gram: Tensor) -> Tensor:
    """σ_max / σ_min of a light matrix M from its Gram matrix A = MᵀM; (..., 3, 3) → (...)."""
    lo, hi = _sym3_extreme_eigenvalues(gram)
    lo, hi = lo.clamp_min(0.0), hi.clamp_min(0.0)
    ratio = torch.where(
        lo > 0, hi / torch.where(lo > 0, lo, torch.ones_like(lo)), torch.full_like(lo, math.inf)
    )
    return ratio.sqrt().to(gram.dtype)


def _outer(lights: Tensor) -> Tensor:
    """(K, 9) flattened outer products L Lᵀ of shared lights (K, 3)."""
    return (lights.unsqueeze(-1) * lights.unsqueeze(-2)).reshape(-1, 9)


def _normal_equations(flat: _Flat, weights: Tensor) -> tuple[Tensor, Tensor]:
    """A = Σ w E² L Lᵀ (P, 3, 3) and r = Σ w E I L (P, 3) for observation weights (K, P)."""
    we2 = weights * flat.light_intensity**2  # (K, P)
    wei = weights * flat.light_intensity * flat.intensity  # (K, P)
    if flat.lights.ndim == 2:  # shared lights: two matrix products with the K outer products L Lᵀ
        gram = (we2.T @ _outer(flat.lights)).reshape(-1, 3, 3)
        rhs = wei.T @ flat.lights
    else:
        gram = torch.einsum("kp,kpi,kpj->pij", we2, flat.lights, flat.lights)
        rhs = torch.einsum("kp,kpi->pi", wei, flat.lights)
    return gram, rhs


def _adjugate_sym3(a: Tensor) -> tuple[Tensor, Tensor]:
    """Adjugate (P, 3, 3) and determinant (P,) of symmetric 3×3 matrices (P, 3, 3)."""
    a00, a11, a22, a01, a02, a12 = _sym3_entries(a)
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    adj = torch.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], -1).reshape(-1, 3, 3)
    det = a00 * c00 + a01 * c01 + a02 * c02
    return adj, det


def _solve_sym3(gram: Tensor, rhs: Tensor, max_condition: float) -> tuple[Tensor, Tensor, Tensor]:
    """Least-squares solve of A b = r per pixel; min-norm where A is (nearly) singular.

    Args:
        gram: (P, 3, 3) symmetric positive semi-definite A.
        rhs: (P, 3).
        max_condition: pixels with cond(M) = sqrt(cond(A)) above this use the pseudo-inverse.

    Returns:
        b (P, 3), A⁻¹ or A⁺ (P, 3, 3), condition σ_max/σ_min of M (P,) (inf when singular).
    """
    dtype = gram.dtype
    # Scale each A to unit trace so the determinant neither under- nor overflows.
    scale = gram.diagonal(dim1=-2, dim2=-1).sum(-1)  # (P,)
    safe_scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    a = gram / safe_scale[:, None, None]
    adj, det = _adjugate_sym3(a)
    cond = _condition_from_gram(a)  # (P,)
    good = (scale > 0) & (det > 0) & (cond <= max_condition)
    safe_det = torch.where(good, det, torch.ones_like(det))
    inv = adj / safe_det[:, None, None] / safe_scale[:, None, None]  # (P, 3, 3)
    bad = ~good
    if _any_true(bad):
        # Minimum-norm least squares through the pseudo-inverse (eigen-decomposition of A).
        eigval, eigvec = torch.linalg.eigh(a[bad])  # (B, 3), (B, 3, 3)
        rtol = 1e3 * torch.finfo(dtype).eps
        keep = eigval > rtol * eigval[:, -1:].clamp_min(torch.finfo(dtype).tiny)
        inv_val = torch.where(
            keep, 1.0 / torch.where(keep, eigval, torch.ones_like(eigval)), torch.zeros_like(eigval)
        )
        pinv = (eigvec * inv_val[:, None, :]) @ eigvec.transpose(-1, -2) / safe_scale[bad, None, None]
        inv = inv.clone()
        inv[bad] = pinv
    b = (inv @ rhs.unsqueeze(-1)).squeeze(-1)  # (P, 3)
    return b, inv, cond


def _residual(flat: _Flat, b: Tensor) -> Tensor:
    """Residuals I − E L·b (K, P) of a fit b (P, 3)."""
    k, p = flat.intensity.shape
    l_dot_b = flat.lights @ b.T if flat.lights.ndim == 2 else (flat.lights * b.unsqueeze(0)).sum(-1)  # (K, P)
    return flat.intensity - flat.light_intensity.expand(k, p) * l_dot_b


def _residual_and_leverage(flat: _Flat, b: Tensor, inv: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Residuals I − E L·b (K, P) and leverages h = w E² Lᵀ A⁻¹ L (K, P) of a weighted fit."""
    k, p = flat.intensity.shape
    if flat.lights.ndim == 2:
        leverage = _outer(flat.lights) @ inv.reshape(-1, 9).T  # (K, P) = Lᵀ A⁻¹ L
    else:
        leverage = torch.einsum("kpi,pij,kpj->kp", flat.lights, inv, flat.lights)
    leverage = (leverage * flat.light_intensity.expand(k, p) ** 2 * weights).clamp(0.0, 1.0)
    return _residual(flat, b), leverage


def _threshold(flat: _Flat, b: Tensor, outlier_rel: float, noise_part: Tensor) -> Tensor:
    """Outlier threshold τ (K, P) = max(outlier_rel · |b| · E_k, noise_part), strictly > 0."""
    k, p = flat.intensity.shape
    relative = outlier_rel * b.norm(dim=-1).unsqueeze(0) * flat.light_intensity.expand(k, p)
    return torch.maximum(relative, noise_part).clamp_min(torch.finfo(b.dtype).tiny)


def _normals_from_b(b: Tensor, view: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Unit normals (P, 3) facing the camera, albedo (P,) and a back-facing flag (P,) from b = ρN."""
    albedo = b.norm(dim=-1)  # (P,)
    tiny = torch.finfo(b.dtype).tiny
    nonzero = albedo > tiny**0.5
    view = view.expand_as(b)
    n = torch.where(
        nonzero[:, None], b / torch.where(nonzero, albedo, torch.ones_like(albedo))[:, None], view
    )
    n_dot_v = (n * view).sum(-1, keepdim=True)  # (P, 1)
    back = n_dot_v.squeeze(-1) < 0
    n = torch.where(back[:, None], n - 2.0 * n_dot_v * view, n)  # flip rule: mirror across ⟂ V
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(tiny)
    albedo = torch.where(nonzero, albedo, torch.zeros_like(albedo))
    return n, albedo, back


# --------------------------------------------------------------------------------------------
# Robust fit: the steps of robust_lambertian_ps
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _RobustOptions:
    """The scalar options of :func:`robust_lambertian_ps` (meanings in its docstring), checked on creation."""

    dark_rel: float
    dark_abs: float
    saturation: float | None
    outlier_rel: float
    noise_std: float
    outlier_sigma: float
    max_trims: int | None
    max_leverage: float
    max_condition: float

    def __post_init__(self) -> None:
        for name in ("dark_rel", "dark_abs", "outlier_rel", "noise_std", "outlier_sigma"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be finite and ≥ 0; got {value}")
        if self.max_trims is not None and self.max_trims < 0:
            raise ValueError(f"max_trims must be ≥ 0; got {self.max_trims}")
        if not 0 < self.max_leverage <= 1:
            raise ValueError(f"max_leverage must be in (0, 1]; got {self.max_leverage}")
        if not self.max_condition >= 1:
            raise ValueError(f"max_condition must be ≥ 1; got {self.max_condition}")
        if self.saturation is not None and not math.isfinite(self.saturation):
            raise ValueError(f"saturation must be finite or None; got {self.saturation}")


def _select_lit(flat: _Flat, opts: _RobustOptions) -> Tensor:
    """Step 1: observations (K, P) that are finite, unmasked, not in shadow and not saturated."""
    zero = torch.zeros((), dtype=flat.intensity.dtype, device=flat.intensity.device)
    e_safe = torch.where(
        flat.light_intensity > 0, flat.light_intensity, torch.ones_like(flat.light_intensity)
    )
    shading = flat.intensity / e_safe  # (K, P) = albedo · N·L for a Lambertian observation
    brightest = torch.where(flat.obs_mask, shading, torch.full_like(shading, -math.inf)).amax(0)  # (P,)
    brightest = torch.where(torch.isfinite(brightest), brightest, zero)
    dark_threshold = torch.clamp(opts.dark_rel * brightest, min=opts.dark_abs)  # (P,)
    used = flat.obs_mask & (shading > dark_threshold.unsqueeze(0))
    if opts.saturation is not None:
        used = used & (flat.intensity < opts.saturation)
    return used


def _subset(flat: _Flat, index: Tensor) -> _Flat:
    """The inputs of the pixels ``index`` (A,) int64 of ``flat``; shared lights, E and V stay shared."""
    # (index_select: several times faster than advanced indexing on the CPU)
    lights = flat.lights if flat.lights.ndim == 2 else flat.lights.index_select(1, index)
    e = flat.light_intensity if flat.light_intensity.shape[1] == 1 else flat.light_intensity.index_select(1, index)
    view = flat.view if flat.view.shape[0] == 1 else flat.view.index_select(0, index)
    return _Flat(flat.intensity.index_select(1, index), lights, e, flat.pixel_mask.index_select(0, index),
                 flat.obs_mask.index_select(1, index), view,
                 (int(index.numel()),))


def _trim_highlights(
    flat: _Flat, used: Tensor, opts: _RobustOptions
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Step 2: fit, drop each pixel's worst positive outlier, refit, up to ``max_trims`` rounds.

    Only the pixels that lost an observation in a round are refitted and tested again (the active
    set): a pixel whose observations did not change has the same fit and no candidate, so the
    result is that of refitting every pixel every round, at the cost of the few pixels under a
    highlight (at 1024² most pixels leave after the first round).

    Args:
        flat: the prepared inputs (K lights, P pixels).
        used: (K, P) bool, the observations step 1 kept.
        opts: the checked options.

    Returns:
        used (K, P) after trimming, and the final fit on it: b (P, 3), A⁻¹ or A⁺ (P, 3, 3),
        condition (P,).
    """
    k = flat.intensity.shape[0]
    dtype = flat.intensity.dtype
    trims = max(k - 3, 0) if opts.max_trims is None else opts.max_trims
    used = used.clone()
    gram, rhs = _normal_equations(flat, _weights(used, dtype))
    b, inv, cond = _solve_sym3(gram, rhs, opts.max_condition)  # (P, 3), (P, 3, 3), (P,)
    index = torch.arange(used.shape[1], device=used.device)  # (A,) the active pixels
    sub, sub_used, sub_b, sub_inv = flat, used, b, inv
    for _ in range(trims):
        remove = _worst_outliers(sub, sub_used, sub_b, sub_inv, _weights(sub_used, dtype), opts)  # (K, A)
        if remove is None:
            break
        changed = _any_along(remove, 0).nonzero().squeeze(1)  # (A',) positions within the active set
        index = index.index_select(0, changed)
        sub_used = (sub_used & ~remove).index_select(1, changed)
        sub = _subset(flat, index)
        gram, rhs = _normal_equations(sub, _weights(sub_used, dtype))
        sub_b, sub_inv, sub_cond = _solve_sym3(gram, rhs, opts.max_condition)
        used.index_copy_(1, index, sub_used)
        b.index_copy_(0, index, sub_b)
        inv.index_copy_(0, index, sub_inv)
        cond.index_copy_(0, index, sub_cond)
    return used, b, inv, cond


def _worst_outliers(
    flat: _Flat, used: Tensor, b: Tensor, inv: Tensor, weights: Tensor, opts: _RobustOptions
) -> Tensor | None:
    """Per pixel, the one removable observation with the largest deleted residual over τ.

    Args:
        flat: the prepared inputs (K lights, P pixels).
        used: (K, P) bool, the observations of the current fit.
        b: (P, 3) the current fit; inv: (P, 3, 3) its A⁻¹ (or A⁺).
        weights: (K, P) ``used`` as the fit's dtype.
        opts: the checked options.

    Returns:
        (K, P) bool with at most one True per pixel, or None when no pixel has a candidate.
    """
    dtype = flat.intensity.dtype
    residual, leverage = _residual_and_leverage(flat, b, inv, weights)  # (K, P) each
    one_minus_h = (1.0 - leverage).clamp_min(torch.finfo(dtype).eps)
    deleted = residual / one_minus_h  # error of predicting I_k from the other observations
    tau = _threshold(flat, b, opts.outlier_rel, opts.outlier_sigma * opts.noise_std / one_minus_h.sqrt())
    n_used = _count(used, 0).unsqueeze(0)  # (1, P)
    candidate = used & (deleted > tau) & (leverage < opts.max_leverage) & (n_used >= 4)
    if not _any_true(candidate):
        return None
    score = torch.where(candidate, deleted / tau, torch.full_like(deleted, -math.inf))
    return _first_max(score) & candidate


def _first_max(score: Tensor) -> Tensor:
    """(K, P) bool, True at the first largest of each column of ``score`` (K, P) — ``argmax(0)`` as a
    one-hot mask, by a running maximum over the K rows (an ``argmax`` across the short leading axis
    was the largest single cost of robust PS)."""
    best = score[0].clone()  # (P,)
    row = torch.zeros(best.shape, dtype=torch.uint8 if score.shape[0] <= 256 else torch.int64, device=score.device)
    for k in range(1, score.shape[0]):
        better = score[k] > best  # strictly: ties keep the first
        best = torch.maximum(best, score[k])  # (scores are never NaN)
        row.masked_fill_(better, k)
    ks = torch.arange(score.shape[0], device=score.device, dtype=row.dtype).unsqueeze(1)  # (K, 1)
    return ks == row.unsqueeze(0)


def _inconsistent(flat: _Flat, used: Tensor, b: Tensor, opts: _RobustOptions) -> Tensor:
    """Pixels (P,) bool where a used observation (K, P) misses the final fit b (P, 3) by more than τ.

    Such a pixel's trimming could not isolate the highlight (too many contaminated lights) or the
    pixel is not Lambertian.
    """
    residual = _residual(flat, b)
    noise_part = torch.full_like(residual, opts.outlier_sigma * opts.noise_std)  # (K, P)
    tau = _threshold(flat, b, opts.outlier_rel, noise_part)
    return _any_along(used & (residual.abs() > tau), 0)


def _reasons(
    pixel_mask: Tensor,
    n_used: Tensor,
    cond: Tensor,
    back: Tensor,
    inconsistent: Tensor,
    max_condition: float,
    degenerate: PSReason | None,
) -> Tensor:
    """Step 3: per-pixel :class:`PSReason` codes (P,) int64 from (P,) flags and counts.

    A later rule overrides an earlier one (MASKED wins over all); ``degenerate`` (the full light
    set's code, or None) marks every pixel that would otherwise be OK.
    """
    reason = torch.full(pixel_mask.shape, int(PSReason.OK), dtype=torch.int64, device=pixel_mask.device)
    reason = torch.where(inconsistent, torch.full_like(reason, int(PSReason.INCONSISTENT)), reason)
    reason = torch.where(back, torch.full_like(reason, int(PSReason.BACK_FACING)), reason)
    reason = torch.where(cond > max_condition, torch.full_like(reason, int(PSReason.ILL_CONDITIONED)), reason)
    reason = torch.where(n_used < 3, torch.full_like(reason, int(PSReason.TOO_FEW_LIGHTS)), reason)
    if degenerate is not None:
        reason = torch.where(reason == int(PSReason.OK), torch.full_like(reason, int(degenerate)), reason)
    return torch.where(pixel_mask, reason, torch.full_like(reason, int(PSReason.MASKED)))


def _log_reasons(reason: Tensor) -> None:
    """Debug-log how many pixels got each :class:`PSReason`; reason (P,) int64."""
    if logger.isEnabledFor(logging.DEBUG):
        counts = torch.bincount(reason, minlength=len(PSReason)).tolist()
        logger.debug("robust PS: %s", {r.name: counts[r.value] for r in PSReason})


# --------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------


def lambertian_ps(
    intensity: Tensor,
    lights: Tensor,
    light_intensity: Tensor | None = None,
    mask: Tensor | None = None,
    *,
    view_dirs: Tensor | None = None,
    max_condition: float = 1e3,
    allow_degenerate: bool = False,
) -> tuple[Tensor, Tensor]:
    """Plain Lambertian photometric stereo: one least-squares fit per pixel over all observations.

    Every (finite, unmasked) observation is used, shadowed and specular ones included: this is
    the textbook estimator, exact for unshadowed Lambertian data. Use
    :func:`robust_lambertian_ps` when shadows or highlights are present.

    Args:
        intensity: (K, P) or (K, H, W) — generally (K, *S) — linear intensities, K lights first.
            Non-finite values are ignored (treated as masked observations).
        lights: (K, 3) unit directions surface → light, camera frame (directional lights), or
            (K, *S, 3) per pixel (point lights; put the 1/r² fall-off into ``light_intensity``).
        light_intensity: (K,) or (K, *S) relative intensities E ≥ 0 (default all 1; 0 disables).
        mask: None, a (*S,) bool pixel mask (False pixels get N = V, albedo 0) or a (K, *S) bool
            observation mask (False observations are left out of that pixel's fit).
        view_dirs: None (orthographic, V = (0, 0, -1)), (3,) or (*S, 3) unit directions surface →
            camera; only used by the flip rule.
        max_condition: largest accepted condition number σ_max/σ_min of the E-weighted light
            matrix; above it the light set counts as coplanar.
        allow_degenerate: with fewer than 3 lights or coplanar lights, return the minimum-norm
            least-squares answer (logged as a warning) instead of raising ValueError.

    Returns:
        normals (*S, 3): unit, camera frame, ``N · V ≥ 0`` (flip rule: see the module docstring).
        albedo (*S,): ≥ 0, such that ``I ≈ albedo · E · (N · L)``.

    Raises:
        ValueError: bad shapes, non-unit or non-finite lights, fewer than 3 lights or coplanar
            lights (unless ``allow_degenerate``).
    """
    flat = _prepare(intensity, lights, light_intensity, mask, view_dirs)
    _check_light_geometry(flat, max_condition, allow_degenerate)
    weights = _weights(flat.obs_mask, flat.intensity.dtype)  # (K, P)
    gram, rhs = _normal_equations(flat, weights)
    b, _, _ = _solve_sym3(gram, rhs, max_condition)
    normals, albedo, _ = _normals_from_b(b, flat.view)
    return normals.reshape(*flat.spatial, 3), albedo.reshape(flat.spatial)


def robust_lambertian_ps(
    intensity: Tensor,
    lights: Tensor,
    light_intensity: Tensor | None = None,
    mask: Tensor | None = None,
    *,
    view_dirs: Tensor | None = None,
    dark_rel: float = 0.02,
    dark_abs: float = 0.0,
    saturation: float | None = None,
    outlier_rel: float = 0.03,
    noise_std: float = 0.0,
    outlier_sigma: float = 4.0,
    max_trims: int | None = None,
    max_leverage: float = 0.95,
    max_condition: float = 30.0,
    allow_degenerate: bool = False,
) -> RobustPSResult:
    """Lambertian photometric stereo that discards shadowed and specular observations.

    Per pixel:

    1. **Shadows / saturation.** An observation is dropped when ``I/E ≤ max(dark_abs,
       dark_rel · max_k I_k/E_k)`` (attached or cast shadow: the Lambertian model's ``max(0, ·)``
       is not linear there), when ``I ≥ saturation`` (a clipped value is only a lower bound), or
       when it is non-finite or masked.
    2. **Highlights.** Fit b by least squares, then compute for every used observation its
       *deleted residual* ``d_k = r_k / (1 − h_k)`` — the error of predicting ``I_k`` from the
       other observations (``r`` the residual, ``h`` the leverage ``w E² Lᵀ A⁻¹ L``). The
       observation with the largest ``d_k / τ_k`` among those with ``d_k > τ_k``,
       ``τ_k = max(outlier_rel · albedo · E_k, outlier_sigma · noise_std / sqrt(1 − h_k))``, is
       removed (only positive residuals: a highlight adds light), provided at least 4 remain
       before removal and ``h_k < max_leverage`` (an observation the fit cannot do without
       cannot be tested). Repeat up to ``max_trims`` times, one observation per pixel per round.
    3. **Flags.** Pixels with fewer than 3 used observations, or whose used lights have a
       condition number above ``max_condition`` (nearly coplanar), or whose fit points away
       from the camera, or where a used observation still misses the final fit by more than
       ``max(outlier_rel · albedo · E_k, outlier_sigma · noise_std)``, are flagged invalid with a
       :class:`PSReason`; they still get a finite (minimum-norm / flipped) normal, never NaN.

    Limitation: trimming starts from the least-squares fit of all lit observations, so it
    isolates highlights that touch a minority of a pixel's lights (sharp lobes); a broad lobe
    over about half of the lit lights can steer it to the wrong subset. Such pixels are often,
    not always, caught by the INCONSISTENT flag.

    Args:
        intensity: (K, *S), e.g. (K, P) or (K, H, W), linear intensities.
        lights: (K, 3) or (K, *S, 3) unit directions surface → light, camera frame.
        light_intensity: (K,) or (K, *S) relative intensities E ≥ 0 (default 1).
        mask: None, (*S,) bool pixel mask, or (K, *S) bool observation mask.
        view_dirs: None (orthographic V = (0, 0, -1)), (3,) or (*S, 3), surface → camera.
        dark_rel: shadow threshold relative to the pixel's brightest (E-normalised) observation.
        dark_abs: absolute shadow threshold on I/E (set it a few noise σ above 0 for noisy data).
        saturation: intensities ≥ this are dropped (e.g. 1.0 for normalised clipped images).
        outlier_rel: highlight threshold relative to the fitted albedo · E_k.
        noise_std: intensity noise σ (absolute), for the noise-based part of the threshold.
        outlier_sigma: multiple of the deleted-residual noise σ used in the threshold.
        max_trims: most highlight observations removed per pixel (default K − 3).
        max_leverage: observations with a larger leverage are never removed.
        max_condition: largest accepted condition number of a pixel's used light matrix; also the
            limit above which the *full* light set counts as coplanar (ValueError).
        allow_degenerate: with < 3 lights or coplanar lights, return minimum-norm normals with
            ``valid = False`` everywhere (reason TOO_FEW_LIGHTS / ILL_CONDITIONED) instead of
            raising.

    Returns:
        :class:`RobustPSResult` (normals (*S, 3), albedo (*S,), valid, reason, used, n_used,
        condition).

    Raises:
        ValueError: invalid shapes or values, fewer than 3 lights, coplanar lights (unless
            ``allow_degenerate``).
    """
    opts = _RobustOptions(
        dark_rel=dark_rel,
        dark_abs=dark_abs,
        saturation=saturation,
        outlier_rel=outlier_rel,
        noise_std=noise_std,
        outlier_sigma=outlier_sigma,
        max_trims=max_trims,
        max_leverage=max_leverage,
        max_condition=max_condition,
    )
    flat = _prepare(intensity, lights, light_intensity, mask, view_dirs)
    degenerate = _check_light_geometry(flat, max_condition, allow_degenerate)
    k, p = flat.intensity.shape

    # Pixels without a single observation (the background of an image) have a known answer — N = V,
    # albedo 0, no light used — so only the others are fitted (a 1024² image is ~30 % background).
    index = _any_along(flat.obs_mask, 0).nonzero().squeeze(1)  # (A,)
    sub = flat if index.numel() == p else _subset(flat, index)
    used_a = _select_lit(sub, opts)  # (K, A)
    used_a, b, _, cond_a = _trim_highlights(sub, used_a, opts)  # (K, A), (A, 3), A⁻¹ (A, 3, 3), (A,)
    inconsistent_a = _inconsistent(sub, used_a, b, opts)  # (A,)
    normals_a, albedo_a, back_a = _normals_from_b(b, sub.view)

    used = torch.zeros_like(flat.obs_mask)
    used.index_copy_(1, index, used_a)
    n_used = _count(used, 0)  # (P,)
    normals = flat.view.expand(p, 3).clone()
    normals.index_copy_(0, index, normals_a)
    albedo = torch.zeros(p, dtype=albedo_a.dtype, device=albedo_a.device)
    albedo.index_copy_(0, index, albedo_a)
    back = torch.zeros(p, dtype=torch.bool, device=used.device)
    back.index_copy_(0, index, back_a)
    inconsistent = torch.zeros_like(back)
    inconsistent.index_copy_(0, index, inconsistent_a)
    cond = torch.full((p,), math.inf, dtype=cond_a.dtype, device=cond_a.device)
    cond.index_copy_(0, index, cond_a)
    cond = torch.where(n_used >= 3, cond, torch.full_like(cond, math.inf))
    code = (PSReason.TOO_FEW_LIGHTS if k < 3 else PSReason.ILL_CONDITIONED) if degenerate else None
    reason = _reasons(flat.pixel_mask, n_used, cond, back, inconsistent, max_condition, code)
    masked = ~flat.pixel_mask
    normals = torch.where(masked[:, None], flat.view.expand_as(normals), normals)
    albedo = torch.where(masked, torch.zeros((), dtype=albedo.dtype, device=albedo.device), albedo)
    _log_reasons(reason)

    s = flat.spatial
    return RobustPSResult(
        normals=normals.reshape(*s, 3),
        albedo=albedo.reshape(s),
        valid=(reason == int(PSReason.OK)).reshape(s),
        reason=reason.reshape(s),
        used=used.reshape(k, *s),
        n_used=n_used.reshape(s),
        condition=cond.reshape(s),
    )
