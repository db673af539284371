"""Surface-normal cues from polarisation: azimuth from AoLP, zenith from DoLP (diffuse/specular).

Conventions (spec §1, §5):

* Stokes ``s = (s0, s1, s2)`` in the pixel's Stokes frame; orthographic camera: ``e_x = x̂`` (image
  right), ``e_y = ŷ`` (image down). AoLP ``φ = ½ atan2(s2, s1)`` ∈ (−π/2, π/2], measured from
  ``e_x`` toward ``e_y``; DoLP ``ρ = √(s1² + s2²) / s0``.
* Normal **azimuth** ``ψ = atan2(N·e_y, N·e_x)`` (orthographic: ``atan2(n_y, n_x)``), the same angle
  convention as the AoLP. Normal **zenith** ``θ = ∠(N, V)`` with ``V`` the direction surface →
  camera (orthographic ``V = (0, 0, −1)``, so ``cos θ = −n_z``). Hence
  ``N = sin θ (cos ψ e_x + sin ψ e_y) + cos θ V``.
* Diffuse (body) light leaves through Fresnel transmission, polarised ∥ to the plane of
  incidence (the plane of N and V): ``φ = ψ (mod π)`` → azimuth candidates ``{φ, φ + π}``.
  Specular reflection is polarised ⟂ to it: ``φ = ψ + π/2 (mod π)`` → candidates ``{φ ± π/2}``.
* Diffuse DoLP (Atkinson & Hancock) for index of refraction ``μ``::

      ρ_d(θ; μ) = (μ − 1/μ)² sin²θ / (2 + 2μ² − (μ + 1/μ)² sin²θ + 4 cos θ √(μ² − sin²θ))

  which equals ``−T−/T+`` of spec §5 (θ < π/2) and rises monotonically from 0 at θ = 0 to
  ``(μ² − 1)/(μ² + 1)`` at θ = π/2. Specular DoLP ``ρ_s(θ; μ) = R−/R+`` (spec §5) rises from 0
  to 1 at Brewster's angle ``atan μ`` and falls back to 0 at π/2: two zenith branches.

Where the cues help: the AoLP fixes the azimuth up to the π (diffuse) or π/2 (specular)
ambiguity wherever the DoLP is above the noise; a reference normal (e.g. Lambertian photometric
stereo) resolves the ambiguity. The diffuse DoLP is small near frontal view (μ = 1.5: ρ_d ≈
0.007 at 20°, 0.033 at 40°, 0.096 at 60°, 0.25 at 80°), so the DoLP-based zenith is reliable
only for diffuse pixels with zenith ≳ 40° and a DoLP well above its noise, and it depends on μ;
elsewhere the reference zenith is the better choice (``zenith_from="reference"``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from polarshape.brdf.fresnel import fresnel

logger = logging.getLogger(__name__)

__all__ = [
    "PolarizationNormals",
    "azimuth_candidates",
    "diffuse_dolp",
    "disambiguate_azimuth",
    "normal_azimuth",
    "normals_from_angles",
    "normals_from_polarization",
    "select_closest_normal",
    "specular_dolp",
    "stokes_to_aolp_dolp",
    "zenith_from_diffuse_dolp",
    "zenith_from_specular_dolp",
]

Model = Literal["diffuse", "specular"]


# --------------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------------


def _as_ior(ior: float | Tensor, like: Tensor) -> Tensor:
    ior_t = torch.as_tensor(ior, dtype=like.dtype, device=like.device)
    if not bool(torch.isfinite(ior_t).all()) or bool((ior_t <= 1.0).any()):
        raise ValueError(f"ior (index of refraction μ) must be finite and > 1 (typical 1.2–2.0); got {ior}")
    return ior_t


def _check_float(name: str, x: Tensor) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor; got {type(x).__name__}")
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor; got dtype {x.dtype}")


def _stokes_last(stokes: Tensor, channel_dim: int | None) -> Tensor:
    """Return Stokes with the 3 components last: (..., 3)."""
    _check_float("stokes", stokes)
    if channel_dim is None:
        last3 = stokes.ndim >= 1 and stokes.shape[-1] == 3
        first3 = stokes.ndim == 3 and stokes.shape[0] == 3
        if last3 and first3:
            raise ValueError(
                f"stokes shape {tuple(stokes.shape)} is ambiguous between (..., 3) and (3, H, W); "
                "pass channel_dim=-1 or channel_dim=0"
            )
        if last3:
            return stokes
        if first3:
            return stokes.movedim(0, -1)
        raise ValueError(
            f"stokes must have shape (..., 3) or (3, H, W) holding (s0, s1, s2); got {tuple(stokes.shape)}"
        )
    if stokes.ndim == 0 or stokes.shape[channel_dim] != 3:
        raise ValueError(
            f"stokes must have size 3 along channel_dim={channel_dim}; got shape {tuple(stokes.shape)}"
        )
    return stokes.movedim(channel_dim, -1)


def _view_frame(view_dirs: Tensor | None, like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Stokes frame (e_x, e_y) and V, each (..., 3) broadcastable (spec §1)."""
    if view_dirs is None:
        e_x = torch.tensor([1.0, 0.0, 0.0], dtype=like.dtype, device=like.device)
        e_y = torch.tensor([0.0, 1.0, 0.0], dtype=like.dtype, device=like.device)
        v = torch.tensor([0.0, 0.0, -1.0], dtype=like.dtype, device=like.device)
        return e_x, e_y, v
    _check_float("view_dirs", view_dirs)
    v = view_dirs.to(dtype=like.dtype, device=like.device)
    if v.shape[-1] != 3:
        raise ValueError(f"view_dirs must have shape (..., 3) (surface → camera); got {tuple(v.shape)}")
    norm = v.norm(dim=-1)
    if not bool(torch.isfinite(v).all()) or bool(((norm - 1.0).abs() > 1e-3).any()):
        raise ValueError("view_dirs must be finite unit vectors (surface → camera)")
    d = -v  # the ray, camera → surface
    x_hat = torch.zeros_like(d)
    x_hat[..., 0] = 1.0
    e_x = x_hat - (d[..., :1]) * d  # x̂ − (x̂·d) d
    e_x = e_x / e_x.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(d.dtype).tiny)
    e_y = torch.linalg.cross(d, e_x, dim=-1)
    return e_x, e_y, v


def _wrap(angle: Tensor) -> Tensor:
    """Wrap to (−π, π]."""
    return torch.atan2(torch.sin(angle), torch.cos(angle))


def _bisect(func, target: Tensor, lo: Tensor, hi: Tensor, increasing: bool, iterations: int) -> Tensor:
    """Vectorised bisection for func(θ) = target on [lo, hi] (func monotonic there)."""
    lo, hi = torch.broadcast_tensors(lo, hi)
    lo, hi = lo.clone(), hi.clone()
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        above = func(mid) > target
        go_left = above if increasing else ~above
        hi = torch.where(go_left, mid, hi)
        lo = torch.where(go_left, lo, mid)
    return 0.5 * (lo + hi)


def _iterations(dtype: torch.dtype) -> int:
    # Halving π/2 this often reaches the dtype's resolution.
    return 56 if dtype == torch.float64 else 28


# --------------------------------------------------------------------------------------------
# Stokes → AoLP / DoLP, azimuth candidates
# --------------------------------------------------------------------------------------------


def stokes_to_aolp_dolp(
    stokes: Tensor, channel_dim: int | None = None, eps: float = 1e-12
) -> tuple[Tensor, Tensor]:
    """AoLP and DoLP of linear Stokes vectors.

    Args:
        stokes: (..., 3) or (3, H, W) holding (s0, s1, s2) in our frame (spec §1). With
            ``channel_dim=None`` the layout is inferred (last axis of size 3, else a leading axis
            of size 3 on a 3-D tensor; ambiguous shapes raise).
        channel_dim: axis of the 3 Stokes components, or None to infer.
        eps: s0 at or below ``eps`` gives DoLP 0.

    Returns:
        aolp (...,) radians in (−π/2, π/2], from image x toward image y (down);
        dolp (...,) ≥ 0 (not clipped at 1; non-finite input gives 0).
    """
    s = _stokes_last(stokes, channel_dim)
    s0, s1, s2 = s.unbind(-1)
    finite = torch.isfinite(s).all(-1)
    zero = torch.zeros((), dtype=s.dtype, device=s.device)
    s0 = torch.where(finite, s0, zero)
    s1 = torch.where(finite, s1, zero)
    s2 = torch.where(finite, s2, zero)
    aolp = 0.5 * torch.atan2(s2, s1)
    lin = torch.sqrt(s1 * s1 + s2 * s2)
    positive = s0 > eps
    dolp = torch.where(positive, lin / torch.where(positive, s0, torch.ones_like(s0)), zero)
    return aolp, dolp


def azimuth_candidates(aolp: Tensor, model: Model = "diffuse") -> Tensor:
    """Candidate normal azimuths from the AoLP: the π (diffuse) or π/2 (specular) ambiguity.

    Args:
        aolp: (...,) radians, our AoLP convention.
        model: "diffuse" (∥ polarisation: ψ ∈ {φ, φ + π}) or "specular" (⟂: ψ ∈ {φ + π/2, φ − π/2}).

    Returns:
        (..., 2) candidate azimuths ψ = atan2(N·e_y, N·e_x) wrapped to (−π, π]; the two
        differ by π.
    """
    _check_float("aolp", aolp)
    if model == "diffuse":
        base = aolp
    elif model == "specular":
        base = aolp + 0.5 * math.pi
    else:
        raise ValueError(f"model must be 'diffuse' or 'specular'; got {model!r}")
    return _wrap(torch.stack([base, base + math.pi], dim=-1))


def normal_azimuth(normals: Tensor, view_dirs: Tensor | None = None) -> Tensor:
    """Azimuth ψ = atan2(N·e_y, N·e_x) (...,) of normals (..., 3) in the pixel Stokes frame.

    Orthographic (``view_dirs=None``): ψ = atan2(n_y, n_x), image y down. 0 for N ∥ V.
    """
    _check_float("normals", normals)
    if normals.shape[-1] != 3:
        raise ValueError(f"normals must have shape (..., 3); got {tuple(normals.shape)}")
    e_x, e_y, _ = _view_frame(view_dirs, normals)
    return torch.atan2((normals * e_y).sum(-1), (normals * e_x).sum(-1))


def normals_from_angles(zenith: Tensor, azimuth: Tensor, view_dirs: Tensor | None = None) -> Tensor:
    """Unit normals (..., 3) from zenith θ = ∠(N, V) and azimuth ψ (broadcast shapes (...)).

    ``N = sin θ (cos ψ e_x + sin ψ e_y) + cos θ V``; orthographic: (sinθ cosψ, sinθ sinψ, −cosθ).
    """
    _check_float("zenith", zenith)
    _check_float("azimuth", azimuth)
    zenith, azimuth = torch.broadcast_tensors(zenith, azimuth)
    e_x, e_y, v = _view_frame(view_dirs, zenith)
    st, ct = torch.sin(zenith).unsqueeze(-1), torch.cos(zenith).unsqueeze(-1)
    sp, cp = torch.sin(azimuth).unsqueeze(-1), torch.cos(azimuth).unsqueeze(-1)
    return st * (cp * e_x + sp * e_y) + ct * v


# --------------------------------------------------------------------------------------------
# DoLP models and their inverses
# --------------------------------------------------------------------------------------------


def diffuse_dolp(zenith: Tensor, ior: float | Tensor) -> Tensor:
    """Diffuse DoLP ρ_d(θ; μ) (formula in the module docstring), θ ∈ [0, π/2] radians.

    Args:
        zenith: (...,) θ = ∠(N, V), radians.
        ior: μ > 1, float or tensor broadcastable with ``zenith``.

    Returns:
        (...,) DoLP in [0, (μ² − 1)/(μ² + 1)].
    """
    _check_float("zenith", zenith)
    mu = _as_ior(ior, zenith)
    s2 = torch.sin(zenith) ** 2
    c = torch.cos(zenith)
    num = (mu - 1.0 / mu) ** 2 * s2
    den = 2.0 + 2.0 * mu**2 - (mu + 1.0 / mu) ** 2 * s2 + 4.0 * c * torch.sqrt((mu**2 - s2).clamp_min(0.0))
    return num / den


def specular_dolp(zenith: Tensor, ior: float | Tensor) -> Tensor:
    """Specular DoLP ρ_s(θ; μ) = R−/R+ = (R_s − R_p)/(R_s + R_p) (spec §5), θ ∈ [0, π/2].

    Args:
        zenith: (...,) angle of incidence = ∠(N, V) for mirror reflection, radians.
        ior: μ > 1, float or broadcastable tensor.

    Returns:
        (...,) DoLP in [0, 1]; 1 at Brewster's angle atan μ.
    """
    _check_float("zenith", zenith)
    fr = fresnel(torch.cos(zenith), _as_ior(ior, zenith))
    return fr.r_minus / fr.r_plus.clamp_min(torch.finfo(zenith.dtype).tiny)


def zenith_from_diffuse_dolp(dolp: Tensor, ior: float | Tensor) -> tuple[Tensor, Tensor]:
    """Invert the diffuse DoLP for the zenith (vectorised bisection on [0, π/2]).

    Args:
        dolp: (...,) measured DoLP.
        ior: μ > 1, float or broadcastable tensor.

    Returns:
        zenith (...,) radians in [0, π/2]; in_range (...,) bool: the DoLP was finite and within
        [0, (μ² − 1)/(μ² + 1)]. Out-of-range values are clamped first (below 0 → 0, above the
        maximum → π/2); non-finite → 0.
    """
    _check_float("dolp", dolp)
    mu = _as_ior(ior, dolp)
    rho_max = (mu**2 - 1.0) / (mu**2 + 1.0)
    finite = torch.isfinite(dolp)
    d = torch.where(finite, dolp, torch.zeros_like(dolp))
    in_range = finite & (d >= 0) & (d <= rho_max)
    target = torch.minimum(d.clamp_min(0.0), rho_max)
    lo = torch.zeros_like(target)
    hi = torch.full_like(target, 0.5 * math.pi)
    zenith = _bisect(lambda t: diffuse_dolp(t, mu), target, lo, hi, True, _iterations(dolp.dtype))
    return zenith, torch.broadcast_to(in_range, zenith.shape)


def zenith_from_specular_dolp(dolp: Tensor, ior: float | Tensor) -> tuple[Tensor, Tensor]:
    """Invert the specular DoLP: both zenith branches (below and above Brewster's angle).

    Args:
        dolp: (...,) measured DoLP.
        ior: μ > 1, float or broadcastable tensor.

    Returns:
        zenith (..., 2) radians: [..., 0] ∈ [0, atan μ], [..., 1] ∈ [atan μ, π/2];
        in_range (...,) bool: the DoLP was finite and in [0, 1] (clamped first otherwise;
        non-finite → 0).
    """
    _check_float("dolp", dolp)
    mu = _as_ior(ior, dolp)
    finite = torch.isfinite(dolp)
    d = torch.where(finite, dolp, torch.zeros_like(dolp))
    in_range = finite & (d >= 0) & (d <= 1)
    target = d.clamp(0.0, 1.0)
    brewster = torch.atan(mu) + torch.zeros_like(target)
    n_iter = _iterations(dolp.dtype)
    func = lambda t: specular_dolp(t, mu)  # noqa: E731
    low = _bisect(func, target, torch.zeros_like(brewster), brewster, True, n_iter)
    high = _bisect(func, target, brewster, torch.full_like(brewster, 0.5 * math.pi), False, n_iter)
    zenith = torch.stack([low, high], dim=-1)
    return zenith, torch.broadcast_to(in_range, low.shape)


# --------------------------------------------------------------------------------------------
# Disambiguation with a reference normal
# --------------------------------------------------------------------------------------------


def disambiguate_azimuth(
    candidates: Tensor, reference_normals: Tensor, view_dirs: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Pick, per pixel, the candidate azimuth closest to the reference normal's azimuth.

    Args:
        candidates: (..., C) azimuths, radians (e.g. from :func:`azimuth_candidates`).
        reference_normals: (..., 3) normals (need not be unit), camera frame, e.g. from
            Lambertian photometric stereo.
        view_dirs: None (orthographic) or (..., 3) unit directions surface → camera.

    Returns:
        azimuth (...,) the chosen candidate; index (...,) int64 into the last axis of
        ``candidates``. Ties (and a reference parallel to V, whose azimuth is undefined) pick
        the first candidate.
    """
    _check_float("candidates", candidates)
    _check_float("reference_normals", reference_normals)
    if reference_normals.shape[-1] != 3:
        raise ValueError(f"reference_normals must have shape (..., 3); got {tuple(reference_normals.shape)}")
    if candidates.shape[:-1] != reference_normals.shape[:-1]:
        raise ValueError(
            f"candidates (..., C) and reference_normals (..., 3) must share the leading shape; got "
            f"{tuple(candidates.shape)} and {tuple(reference_normals.shape)}"
        )
    ref = torch.nan_to_num(reference_normals.to(candidates.dtype), nan=0.0, posinf=0.0, neginf=0.0)
    ref_az = normal_azimuth(ref, view_dirs)  # (...,)
    distance = _wrap(candidates - ref_az.unsqueeze(-1)).abs()  # (..., C)
    distance = torch.nan_to_num(distance, nan=math.inf)
    index = distance.argmin(-1)
    chosen = torch.gather(candidates, -1, index.unsqueeze(-1)).squeeze(-1)
    return chosen, index


def _angle(a: Tensor, b: Tensor) -> Tensor:
    """Angle between vectors (..., 3), radians, via atan2(|a×b|, a·b) (spec §7 numerics)."""
    return torch.atan2(torch.linalg.cross(a, b, dim=-1).norm(dim=-1), (a * b).sum(-1))


def select_closest_normal(candidates: Tensor, reference_normals: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Pick, per pixel, the candidate normal at the smallest angle to the reference.

    Args:
        candidates: (..., C, 3) candidate normals (C ≥ 1), camera frame.
        reference_normals: (..., 3).

    Returns:
        normal (..., 3); index (...,) int64; margin (...,) in [0, 1]: (a₂ − a₁)/(a₂ + a₁) with a₁,
        a₂ the smallest and second-smallest angles to the reference (1 when C = 1), a measure of
        how clear the choice was.
    """
    _check_float("candidates", candidates)
    _check_float("reference_normals", reference_normals)
    if candidates.ndim < 2 or candidates.shape[-1] != 3:
        raise ValueError(f"candidates must have shape (..., C, 3); got {tuple(candidates.shape)}")
    if candidates.shape[:-2] != reference_normals.shape[:-1] or reference_normals.shape[-1] != 3:
        raise ValueError(
            f"candidates (..., C, 3) and reference_normals (..., 3) must share the leading shape; got "
            f"{tuple(candidates.shape)} and {tuple(reference_normals.shape)}"
        )
    ref = torch.nan_to_num(reference_normals.to(candidates.dtype), nan=0.0, posinf=0.0, neginf=0.0)
    angles = _angle(candidates, ref.unsqueeze(-2))  # (..., C)
    angles = torch.nan_to_num(angles, nan=math.inf)
    index = angles.argmin(-1)
    normal = torch.gather(candidates, -2, index[..., None, None].expand(*index.shape, 1, 3)).squeeze(-2)
    if candidates.shape[-2] == 1:
        return normal, index, torch.ones_like(angles[..., 0])
    two = angles.topk(2, dim=-1, largest=False).values  # (..., 2) ascending
    total = two.sum(-1)
    margin = torch.where(
        total > 0,
        (two[..., 1] - two[..., 0]) / torch.where(total > 0, total, torch.ones_like(total)),
        torch.zeros_like(total),
    )
    margin = torch.nan_to_num(margin, nan=0.0).clamp(0.0, 1.0)
    return normal, index, margin


# --------------------------------------------------------------------------------------------
# Combined normals
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PolarizationNormals:
    """Output of :func:`normals_from_polarization`; ``S`` is the pixel shape.

    Attributes:
        normals: (*S, 3) unit normals, camera frame (the reference normal where the
            polarisation is unusable: non-finite Stokes or s0 ≤ 0).
        confidence: (*S,) in [0, 1] = DoLP SNR term ρ²/(ρ² + dolp_noise²) × disambiguation margin
            × range term (1 inside the model's DoLP range, falling linearly to 0 at dolp_noise
            beyond it); 0 where unusable.
        zenith: (*S,) chosen zenith ∠(N, V), radians.
        azimuth: (*S,) chosen azimuth atan2(N·e_y, N·e_x), radians.
        aolp: (*S,) radians; dolp: (*S,) measured.
        in_range: (*S,) bool, DoLP inside the model's range (the zenith was not clamped).
    """

    normals: Tensor
    confidence: Tensor
    zenith: Tensor
    azimuth: Tensor
    aolp: Tensor
    dolp: Tensor
    in_range: Tensor


def normals_from_polarization(
    stokes: Tensor,
    reference_normals: Tensor,
    ior: float | Tensor,
    model: Model = "diffuse",
    *,
    zenith_from: Literal["dolp", "reference"] = "dolp",
    dolp_noise: float = 0.01,
    channel_dim: int | None = None,
    view_dirs: Tensor | None = None,
) -> PolarizationNormals:
    """Normals from polarisation, disambiguated by a reference normal (e.g. photometric stereo).

    The AoLP gives two azimuth candidates (π apart; see :func:`azimuth_candidates`). The zenith
    comes from the DoLP (``zenith_from="dolp"``: one value for the diffuse model, two branches
    for the specular one) or from the reference (``"reference"``, for pixels whose DoLP is too low
    for its zenith to be trusted, or when μ is unknown). Of the resulting 2 (diffuse) or 4
    (specular) candidate normals, the one at the smallest angle to the reference is returned.

    Where it helps: the azimuth from a clean AoLP is sharper than a photometric-stereo azimuth;
    the DoLP zenith is reliable for diffuse pixels with zenith ≳ 40° (μ ≈ 1.5) and a DoLP well
    above ``dolp_noise``, which is what the confidence measures. Frontal pixels (low DoLP) get a
    low confidence: use the reference there.

    Args:
        stokes: (..., 3) or (3, H, W) Stokes (s0, s1, s2), our convention (spec §1); pixel
            shape S = (...) or (H, W).
        reference_normals: (*S, 3) reference normals, camera frame (unit or not).
        ior: μ > 1, float or tensor broadcastable to S.
        model: "diffuse" (body reflection, ∥ polarised) or "specular" (surface reflection, ⟂).
        zenith_from: "dolp" or "reference".
        dolp_noise: DoLP noise level (σ of the measured DoLP), > 0, for the confidence.
        channel_dim: axis of the Stokes components (None: inferred, see
            :func:`stokes_to_aolp_dolp`).
        view_dirs: None (orthographic, V = (0, 0, −1)) or (*S, 3) unit directions surface →
            camera; the Stokes must then be in the per-pixel frame of spec §1.

    Returns:
        :class:`PolarizationNormals`.
    """
    if model not in ("diffuse", "specular"):
        raise ValueError(f"model must be 'diffuse' or 'specular'; got {model!r}")
    if zenith_from not in ("dolp", "reference"):
        raise ValueError(f"zenith_from must be 'dolp' or 'reference'; got {zenith_from!r}")
    if not (math.isfinite(dolp_noise) and dolp_noise > 0):
        raise ValueError(f"dolp_noise must be finite and > 0; got {dolp_noise}")
    s = _stokes_last(stokes, channel_dim)
    pixel_shape = s.shape[:-1]
    _check_float("reference_normals", reference_normals)
    if tuple(reference_normals.shape) != (*pixel_shape, 3):
        raise ValueError(
            f"reference_normals must have shape {(*pixel_shape, 3)} to match stokes {tuple(stokes.shape)}; "
            f"got {tuple(reference_normals.shape)}"
        )
    ref = torch.nan_to_num(
        reference_normals.to(device=s.device, dtype=s.dtype), nan=0.0, posinf=0.0, neginf=0.0
    )
    _, _, v = _view_frame(view_dirs, s)
    ref_norm = ref.norm(dim=-1, keepdim=True)
    ref_unit = torch.where(
        ref_norm > 0, ref / ref_norm.clamp_min(torch.finfo(s.dtype).tiny), v.expand_as(ref)
    )
    mu = _as_ior(ior, s)

    aolp, dolp = stokes_to_aolp_dolp(s, channel_dim=-1)
    usable = torch.isfinite(s).all(-1) & (s[..., 0] > 0)
    azimuths = azimuth_candidates(aolp, model)  # (*S, 2)

    if zenith_from == "reference":
        zen_ref = _angle(ref_unit, v.expand_as(ref_unit))  # (*S,)
        zeniths = zen_ref.unsqueeze(-1)  # (*S, 1)
        in_range = torch.ones_like(usable)
        excess = torch.zeros_like(dolp)
    elif model == "diffuse":
        zen, in_range = zenith_from_diffuse_dolp(dolp, mu)
        zeniths = zen.unsqueeze(-1)
        excess = (dolp - (mu**2 - 1.0) / (mu**2 + 1.0)).clamp_min(0.0)
    else:
        zeniths, in_range = zenith_from_specular_dolp(dolp, mu)  # (*S, 2)
        excess = (dolp - 1.0).clamp_min(0.0)

    # All (zenith, azimuth) combinations: (*S, Z, A) → (*S, Z·A)
    zz = zeniths.unsqueeze(-1).expand(*zeniths.shape, azimuths.shape[-1])
    aa = azimuths.unsqueeze(-2).expand(*zeniths.shape, azimuths.shape[-1])
    zz = zz.reshape(*pixel_shape, -1)
    aa = aa.reshape(*pixel_shape, -1)
    frame = None if view_dirs is None else v.unsqueeze(-2)
    cands = normals_from_angles(zz, aa, frame)  # (*S, C, 3)
    normal, index, margin = select_closest_normal(cands, ref_unit)
    zenith = torch.gather(zz, -1, index.unsqueeze(-1)).squeeze(-1)
    azimuth = torch.gather(aa, -1, index.unsqueeze(-1)).squeeze(-1)

    snr = dolp**2 / (dolp**2 + dolp_noise**2)
    range_term = (1.0 - excess / dolp_noise).clamp(0.0, 1.0)
    confidence = snr * margin * range_term
    confidence = torch.where(usable, confidence, torch.zeros_like(confidence))
    normal = torch.where(usable.unsqueeze(-1), normal, ref_unit)
    zenith = torch.where(usable, zenith, _angle(ref_unit, v.expand_as(ref_unit)))
    azimuth = torch.where(usable, azimuth, normal_azimuth(ref_unit, view_dirs))
    if logger.isEnabledFor(logging.DEBUG):
        logger.debug(
            "polarisation normals (%s, zenith from %s): %d px, %.1f%% usable, %.1f%% DoLP in range, "
            "mean confidence %.3f",
            model,
            zenith_from,
            usable.numel(),
            100.0 * float(usable.float().mean()),
            100.0 * float(in_range.float().mean()),
            float(confidence.mean()),
        )
    return PolarizationNormals(
        normals=normal,
        confidence=confidence,
        zenith=zenith,
        azimuth=azimuth,
        aolp=aolp,
        dolp=dolp,
        in_range=in_range & usable,
    )
