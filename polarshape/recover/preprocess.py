"""Capture → recovery tensors: super-pixel Stokes, observation validity, mask, lights, view directions.

Everything the recovery stage needs from a :class:`polarshape.io.capture.Capture`, at super-pixel
resolution (H, W) = (frame height / 2, frame width / 2). Where in each 2×2 block the Stokes vector
is taken (``sample_at``) and how (``demosaic``):

- ``demosaic="bilinear"`` (default): every polariser image is interpolated to every site
  (:func:`polarshape.imaging.demosaic.stokes_from_mosaic`), so the four intensities of a Stokes
  vector belong to one point; ``sample_at="centre"`` averages the block's four such vectors (the
  block's centre, where the simulator's ground truth is), a corner name takes that site's vector
  (e.g. ``"top_left"``: a ground truth given at the IMX250MZR's 90° site). The super-pixel
  estimate instead combines four sites half a pixel apart: under an intensity gradient this adds a
  spurious s1, s2 (measured on the default sphere: 0.33° → 0.19° mean normal error with bilinear).
- ``demosaic="superpixel"``: the plain 2×2 estimate (``sample_at`` must be ``"centre"``).

- ``stokes`` (K, 3, H, W): linear Stokes (s0, s1, s2) in fractions of full scale (spec §1:
  s0 = ½ ΣI, s1 = I0 − I90, s2 = I45 − I135), **in each pixel's Stokes frame** (spec §1). A
  perspective capture stores angles in the sensor-plane convention; they are mapped back here.
- ``valid`` (K, H, W) bool: the observation is neither dark (s0 below ``dark_threshold`` of full
  scale: no usable polarisation, and possibly shadowed) nor saturated (any of its four sites at the
  top count: the Stokes vector is wrong), and lies in the mask.
- ``mask`` (H, W) bool object mask (the capture's mask, or every pixel lit in ≥ 3 observations).
- ``lights`` (K, 3) unit directions surface → light (directional), camera frame, and
  ``irradiance`` (K,) relative intensities E_k. Point lights need surface points (unknown before
  recovery): :func:`preprocess_capture` accepts ``points`` (H, W, 3) and then returns per-pixel
  ``lights`` (K, H, W, 3) and ``irradiance`` (K, H, W) with the 1/r² fall-off.
- ``view`` (H, W, 3) unit directions surface → camera (orthographic: (0, 0, −1)).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from polarshape.imaging.demosaic import stokes_from_mosaic
from polarshape.imaging.mosaic import MosaicLayout, split_mosaic
from polarshape.imaging.pixels import counts_to_float, max_count, reduce_mask_to_superpixels
from polarshape.io.capture import Capture
from polarshape.render import sensor_plane_basis, sensor_plane_stokes

logger = logging.getLogger(__name__)

__all__ = [
    "DEMOSAIC_CHOICES", "POLARISATION_SIGNAL_MIN", "SAMPLE_SITES", "RecoveryInputs", "crop_inputs", "mixed_superpixels", "polarisation_signal", "preprocess_capture",
    "superpixel_stokes", "superpixel_view_directions",
]

#: How the Stokes images are estimated from the mosaic.
DEMOSAIC_CHOICES: tuple[str, ...] = ("bilinear", "superpixel")
#: Where in each 2×2 block the Stokes vector is taken: (row, column) of a site, or None = centre.
SAMPLE_SITES: dict[str, tuple[int, int] | None] = {
    "centre": None, "top_left": (0, 0), "top_right": (0, 1), "bottom_left": (1, 0), "bottom_right": (1, 1),
}


@dataclass(frozen=True)
class RecoveryInputs:
    """Tensors for recovery (super-pixel resolution H × W, K lights); see the module docstring.

    Attributes:
        stokes: (K, 3, H, W) Stokes in each pixel's frame, fraction of full scale.
        valid: (K, H, W) bool usable observations (not dark, not saturated, inside ``mask``).
        saturated: (K, H, W) bool observations with a saturated site.
        mask: (H, W) bool object mask.
        lights: (K, 3) or (K, H, W, 3) unit directions surface → light, camera frame.
        irradiance: (K,) or (K, H, W) relative irradiance E ≥ 0.
        view: (H, W, 3) unit directions surface → camera.
        noise_std: estimated σ of s0 from quantisation and read noise, fraction of full scale.
        has_polarisation: False when the linear Stokes components hold no signal above the noise
            (no polariser, or an unpolarised scene: intensity only), see :func:`polarisation_signal`.
        offset: (row, column) of this grid's pixel (0, 0) in the full super-pixel grid (crops).
    """

    stokes: Tensor
    valid: Tensor
    saturated: Tensor
    mask: Tensor
    lights: Tensor
    irradiance: Tensor
    view: Tensor
    noise_std: float
    has_polarisation: bool
    offset: tuple[int, int] = (0, 0)

    @property
    def num_lights(self) -> int:
        return int(self.stokes.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.stokes.shape[-2]), int(self.stokes.shape[-1])


def superpixel_view_directions(
    capture: Capture, height: int, width: int, *, dtype: torch.dtype = torch.float64, sample_at: str = "centre"
) -> Tensor:
    """(H, W, 3) unit directions surface → camera at each super-pixel's sample point, camera frame.

    Orthographic: (0, 0, −1). Perspective (pinhole at the origin, raw-pixel intrinsics): the
    super-pixel (y, x) covers raw pixels (2y..2y+1, 2x..2x+1); its sample point is the centre
    (2x + 0.5, 2y + 0.5) or the site ``sample_at`` (e.g. top_left: (2x, 2y)); the ray through it,
    undistorted with ``camera.distortion`` when present (OpenCV model, ``cv2.undistortPoints``: the
    frames are not resampled, which would mix the polariser channels), gives V = −normalise(ray).
    """
    if sample_at not in SAMPLE_SITES:
        raise ValueError(f"sample_at must be one of {tuple(SAMPLE_SITES)}; got {sample_at!r}")
    cam = capture.spec.camera
    if cam.projection == "orthographic":
        view = torch.zeros(height, width, 3, dtype=dtype)
        view[..., 2] = -1.0
        return view
    k = cam.intrinsics
    if k is None:
        raise ValueError("capture.yaml: camera.intrinsics are required for a perspective camera")
    site = SAMPLE_SITES[sample_at]
    dy, dx = (0.5, 0.5) if site is None else (float(site[0]), float(site[1]))
    v, u = np.meshgrid(np.arange(height) * 2.0 + dy, np.arange(width) * 2.0 + dx, indexing="ij")
    if cam.distortion is not None and any(abs(c) > 0 for c in cam.distortion):
        import cv2

        matrix = np.array([[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]])
        points = np.stack([u, v], -1).reshape(-1, 1, 2)
        xy = cv2.undistortPoints(points, matrix, np.asarray(cam.distortion, dtype=np.float64)).reshape(height, width, 2)
    else:
        xy = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy], -1)
    ray = torch.from_numpy(np.concatenate([xy, np.ones((height, width, 1))], -1)).to(dtype)
    return -ray / ray.norm(dim=-1, keepdim=True)


def superpixel_stokes(mosaic: Tensor, layout: MosaicLayout, *, demosaic: str = "bilinear", sample_at: str = "centre") -> Tensor:
    """Stokes images (*, 3, H, W) of mosaics (*, 2H, 2W) at one point per 2×2 block (module docstring).

    Raises:
        ValueError: an unknown ``demosaic`` or ``sample_at``, or a corner site with ``"superpixel"``.
    """
    if demosaic not in DEMOSAIC_CHOICES:
        raise ValueError(f"demosaic must be one of {DEMOSAIC_CHOICES}; got {demosaic!r}")
    if sample_at not in SAMPLE_SITES:
        raise ValueError(f"sample_at must be one of {tuple(SAMPLE_SITES)}; got {sample_at!r}")
    site = SAMPLE_SITES[sample_at]
    if demosaic == "superpixel":
        if site is not None:
            raise ValueError(f"sample_at {sample_at!r} needs demosaic 'bilinear' (the super-pixel estimate is at the centre)")
        return stokes_from_mosaic(mosaic, layout, "superpixel")
    full = stokes_from_mosaic(mosaic, layout, "bilinear")  # (*, 3, 2H, 2W)
    if site is None:
        lead = full.shape[:-2]
        return F.avg_pool2d(full.reshape(-1, *full.shape[-2:]).unsqueeze(1), 2).reshape(*lead, *(n // 2 for n in full.shape[-2:]))
    return full[..., site[0]::2, site[1]::2]


def _to_pixel_frames(stokes: Tensor, view: Tensor) -> Tensor:
    """Invert :func:`polarshape.render.sensor_plane_stokes`: sensor-plane angles → per-pixel frames.

    The forward map sends a frame direction (cos φ, sin φ) to M (cos φ, sin φ) (then normalises);
    the inverse is the same construction with M⁻¹ (per pixel 2×2).
    """
    basis = sensor_plane_basis(view.to(torch.float64))  # (H, W, 2, 2)
    inverse = torch.linalg.inv(basis)
    return sensor_plane_stokes(stokes.to(torch.float64), basis=inverse).to(stokes.dtype)


def preprocess_capture(
    capture: Capture,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    dark_threshold: float = 0.005,
    saturation_margin: int = 0,
    points: np.ndarray | None = None,
    mixed_sigma: float | None = 6.0,
    demosaic: str = "bilinear",
    sample_at: str = "centre",
) -> RecoveryInputs:
    """Convert a capture to recovery tensors (super-pixel demosaicing, frames, validity).

    Args:
        capture: the loaded capture (frames (K, 2H, 2W) uint16 counts).
        dtype, device: of the returned tensors.
        dark_threshold: observations with s0 below this fraction of full scale are invalid.
        saturation_margin: counts below the top still treated as saturated.
        points: (H, W, 3) surface points (metres, camera frame), needed only for point lights.
        mixed_sigma: observations whose four sites disagree by more than this many noise σ are
            invalid (see :func:`mixed_superpixels`); None keeps them.
        demosaic, sample_at: how and where each block's Stokes vector is estimated (module docstring).

    Returns:
        :class:`RecoveryInputs`.

    Raises:
        ValueError: point lights without ``points``; a mask of the wrong shape; bad thresholds.
    """
    if not 0 <= dark_threshold < 1:
        raise ValueError(f"dark_threshold must be a fraction of full scale in [0, 1); got {dark_threshold!r}")
    frames = capture.frames
    k, h2, w2 = frames.shape
    h, w = h2 // 2, w2 // 2
    bit_depth = capture.bit_depth
    black = capture.spec.camera.black_level
    mosaic = counts_to_float(frames, bit_depth, black, dtype=torch.float64)  # (K, 2H, 2W)
    stokes = superpixel_stokes(mosaic, capture.layout, demosaic=demosaic, sample_at=sample_at)  # (K, 3, H, W)
    sites = split_mosaic(mosaic, capture.layout)  # (K, 4, H, W) at 0°, 45°, 90°, 135°
    view = superpixel_view_directions(capture, h, w, sample_at=sample_at)  # (H, W, 3) float64
    if capture.spec.camera.projection == "perspective":
        stokes = _to_pixel_frames(stokes, view)

    # a 16-bit format carrying a 12-bit ADC (the IMX250MZR's PolarizeMono16) tops out at 4095·16 =
    # 65520, not 65535: the last 12-bit step counts as saturated
    top = (max_count(bit_depth) if bit_depth < 16 else 65520) - int(saturation_margin)
    saturated_sites = torch.from_numpy(frames.astype(np.int64) >= top)
    saturated = reduce_mask_to_superpixels(saturated_sites, "any")  # (K, H, W)
    if demosaic == "bilinear":  # interpolation reaches one block further: so does a clipped site
        saturated = F.max_pool2d(saturated.to(torch.float32).unsqueeze(1), 3, stride=1, padding=1).squeeze(1) > 0
    dark = sites.mean(1) * 2 < dark_threshold  # (K, H, W): the block's own s0 = ½ Σ of its four sites

    if capture.mask is not None:
        mask = torch.from_numpy(np.asarray(capture.mask, dtype=bool))
        if tuple(mask.shape) != (h, w):
            raise ValueError(f"capture mask has shape {tuple(mask.shape)}; expected the super-pixel shape {(h, w)}")
    else:
        mask = (~dark & ~saturated).sum(0) >= 3
        logger.info("capture has no mask: using the %d pixels lit in ≥ 3 observations", int(mask.sum()))
    mixed = mixed_superpixels(sites, ~dark & ~saturated & mask.unsqueeze(0), n_sigma=mixed_sigma)
    valid = ~dark & ~saturated & ~mixed & mask.unsqueeze(0)

    intensities = torch.from_numpy(capture.light_intensities())  # (K,)
    if any(light.position is not None for light in capture.spec.lights):
        if points is None:
            raise ValueError(
                "capture.yaml has point lights (position): pass points=(H, W, 3) surface points (metres, "
                "camera frame; e.g. from a depth estimate) to preprocess_capture, or calibrate directional lights"
            )
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape != (h, w, 3):
            raise ValueError(f"points must have shape (H, W, 3) = {(h, w, 3)}; got {pts.shape}")
        dirs = torch.from_numpy(capture.light_directions(pts))  # (K, H, W, 3)
        irr = intensities.reshape(k, 1, 1).expand(k, h, w).clone()
        for i, light in enumerate(capture.spec.lights):
            if light.position is not None:
                d2 = ((np.asarray(light.position) - pts) ** 2).sum(-1)
                irr[i] = irr[i] / torch.from_numpy(np.maximum(d2, 1e-12))
        lights, irradiance = dirs, irr
    else:
        lights = torch.from_numpy(capture.light_directions())  # (K, 3)
        lights = lights / lights.norm(dim=-1, keepdim=True)
        irradiance = intensities

    # σ of s0 from quantisation (1 count / √12 per site, ½Σ of 4 sites) plus a read-noise floor.
    step = 1.0 / (max_count(bit_depth) - black)
    noise_std = float(step / np.sqrt(12.0))
    lin = stokes[:, 1:].abs()[valid.unsqueeze(1).expand(-1, 2, -1, -1)]
    has_pol = bool(lin.numel() and float(lin.max()) > 4 * step)
    if has_pol:  # above the quantisation: is it polarisation or only noise?
        signal = polarisation_signal(stokes[:, 1:], sites, valid)
        has_pol = signal >= POLARISATION_SIGNAL_MIN
        logger.debug("preprocess: polarisation signal %.3g (threshold %.2g)", signal, POLARISATION_SIGNAL_MIN)
    out = RecoveryInputs(
        stokes=stokes.to(device=device, dtype=dtype),
        valid=valid.to(device),
        saturated=saturated.to(device),
        mask=mask.to(device),
        lights=lights.to(device=device, dtype=dtype),
        irradiance=irradiance.to(device=device, dtype=dtype),
        view=view.to(device=device, dtype=dtype),
        noise_std=noise_std,
        has_polarisation=has_pol,
    )
    logger.debug("preprocess: K=%d, %dx%d super-pixels, %d in mask, %d valid observations", k, h, w, int(mask.sum()), int(valid.sum()))
    return out


def _site_redundancy(sites: Tensor) -> Tensor:
    """(K, H, W) d = (I0 + I90) − (I45 + I135) of site intensities (K, 4, H, W) at 0°, 45°, 90°, 135°:
    both sums are s0, so d is noise plus whatever differs between the four sites (an edge)."""
    return (sites[:, 0] + sites[:, 2]) - (sites[:, 1] + sites[:, 3])


#: :func:`polarisation_signal` at or above this: the capture is polarised. Measured (12-bit, shot and
#: read noise; ``python benchmarks/recovery_cases.py signal``): no polariser 0.02–0.11; polarising
#: materials 0.77 (rough sphere, α 0.8) to 6.7, official_sphere128 1.25, mitsuba_sphere_a020 15.7.
POLARISATION_SIGNAL_MIN = 0.25


def polarisation_signal(linear: Tensor, sites: Tensor, valid: Tensor) -> float:
    """How much spatially coherent linear polarisation the Stokes images hold, in units of the noise.

    Noise alone does not vanish from s1, s2 (a camera without polariser under shot noise: |s1, s2|
    far above the quantisation step), so "s1 = s2 = 0" cannot be the test. Here the products of
    the linear Stokes vectors of pixels two blocks apart (their interpolation stencils share no
    raw pixel, so their noise is independent and averages out of the product) measure the signal,
    and the four-site redundancy d = (I0 + I90) − (I45 + I135) (pure noise, free of polarisation
    and of first-order gradients) its noise:

        ratio = Σ (s_p · s_q) / Σ ½ (d_p² + d_q²)   over valid pairs p, q = p + 2 along rows and columns.

    Args:
        linear: (K, 2, H, W) s1, s2.
        sites: (K, 4, H, W) site intensities at 0°, 45°, 90°, 135°.
        valid: (K, H, W) bool usable observations.

    Returns:
        The ratio (≥ 0 in practice; inf for noise-free polarised data, 0 without valid pairs).
    """
    d2 = _site_redundancy(sites).to(torch.float64) ** 2
    lin = linear.to(torch.float64)
    num, den = 0.0, 0.0
    for a, b, va, vb, da, db in (
        (lin[..., :-2], lin[..., 2:], valid[..., :-2], valid[..., 2:], d2[..., :-2], d2[..., 2:]),
        (lin[..., :-2, :], lin[..., 2:, :], valid[..., :-2, :], valid[..., 2:, :], d2[..., :-2, :], d2[..., 2:, :]),
    ):
        pair = va & vb
        num += float((a * b).sum(1)[pair].sum())
        den += float((0.5 * (da + db))[pair].sum())
    if den <= 0:
        return math.inf if num > 0 else 0.0
    return max(num, 0.0) / den


def mixed_superpixels(sites: Tensor, usable: Tensor, *, n_sigma: float | None = 6.0) -> Tensor:
    """Observations whose 2×2 block straddles an edge (cast-shadow boundary, silhouette, texture step).

    Four polariser samples over-determine the three linear Stokes components: ideal data satisfy
    I0 + I90 = I45 + I135 (= s0). A block whose sites see different radiance breaks it and its
    Stokes vector shows false polarisation. The discrepancy d = (I0 + I90) − (I45 + I135) is
    normalised by √(s0 + c) (shot noise grows with the signal; c = 10⁻³ is a read-noise floor), its
    σ estimated robustly (1.4826 · MAD over the usable observations), and |d| > ``n_sigma`` σ flags
    the observation.

    Args:
        sites: (K, 4, H, W) site intensities at 0°, 45°, 90°, 135°.
        usable: (K, H, W) bool observations to estimate σ from.
        n_sigma: threshold; None disables the test.

    Returns:
        (K, H, W) bool, True for mixed observations.
    """
    if n_sigma is None:
        return torch.zeros_like(usable)
    s0 = 0.5 * sites.sum(1)
    d = _site_redundancy(sites) / torch.sqrt(s0.clamp_min(0.0) + 1e-3)
    v = d[usable]
    if v.numel() < 16:
        return torch.zeros_like(usable)
    sigma = float((v - v.median()).abs().median()) * 1.4826
    if sigma <= 0:
        return torch.zeros_like(usable)
    mixed = d.abs() > n_sigma * sigma
    logger.debug("mixed super-pixel observations: %d of %d usable", int((mixed & usable).sum()), int(usable.sum()))
    return mixed


def crop_inputs(inputs: RecoveryInputs, margin: int = 0) -> RecoveryInputs:
    """Crop every per-pixel tensor to the bounding box of the mask (plus ``margin`` pixels).

    Returns the inputs unchanged when the mask is empty.
    """
    rows = torch.nonzero(inputs.mask.any(1)).flatten()
    cols = torch.nonzero(inputs.mask.any(0)).flatten()
    if rows.numel() == 0:
        return inputs
    h, w = inputs.shape
    r0, r1 = max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, h)
    c0, c1 = max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, w)
    lights = inputs.lights if inputs.lights.ndim == 2 else inputs.lights[:, r0:r1, c0:c1]
    irr = inputs.irradiance if inputs.irradiance.ndim == 1 else inputs.irradiance[:, r0:r1, c0:c1]
    return replace(
        inputs,
        stokes=inputs.stokes[..., r0:r1, c0:c1],
        valid=inputs.valid[:, r0:r1, c0:c1],
        saturated=inputs.saturated[:, r0:r1, c0:c1],
        mask=inputs.mask[r0:r1, c0:c1],
        lights=lights,
        irradiance=irr,
        view=inputs.view[r0:r1, c0:c1],
        offset=(inputs.offset[0] + r0, inputs.offset[1] + c0),
    )
