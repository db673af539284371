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
- ``camera.polarimetric_calibration`` (capture.yaml): the per-pixel black level replaces the scalar
  ``camera.black_level`` (full scale stays max count − ``camera.black_level``), and every Stokes
  vector comes from the calibrated analysers (:func:`polarshape.imaging.analyser.calibrated_stokes`:
  per block, or with ``bilinear`` per pixel from every angle class and its rows interpolated there);
  defective pixels drop out (three sites determine a block; a block with ≥ 2 defects is invalid)
  and are not taken for clipped.

- colour captures (``camera.mosaic.bayer``, Sony IMX250MYR / Lucid TRI050S-QC: each 2×2 polariser
  block behind one colour filter, a Bayer pattern over the blocks): each block's own colour by the
  plain 2×2 estimate, each site first moved to the block centre with its colour's gradient (the
  super-pixel estimate's spurious s1, s2 under a gradient; measured on ``configs/scenes/colour.yaml``
  before the silhouette rule below: 0.41° → 0.27° mean normal error), and the two other colours
  interpolated bilinearly from the neighbouring blocks of those colours
  (:func:`colour_superpixel_stokes`), so every channel has a Stokes vector at every block centre —
  the super-pixel grid, camera and geometry of a mono capture (``demosaic`` is not used: a
  polariser image interpolated across blocks would mix colours; ``sample_at`` must be ``"centre"``). ``stokes`` is then the channel mean (R + G + B) / 3
  (:func:`combined_colour_stokes`): with white lights the surface term is the same in every
  channel and the body term is linear in k_b, so it is the mono model with k_b the mean of the
  channels' — what normal and material recovery consume; ``RecoveryInputs.colour`` keeps the
  channels (:class:`polarshape.recover.observations.ColourInputs`). At the silhouette a channel
  interpolated from a block outside the mask (the background) is left out of the mean and is
  invalid for that channel (:func:`polarshape.imaging.colour.bayer_reach`; the weights depend on
  the mask only, so a pixel's k_b is the same mean of the channels' under every light; measured on
  ``configs/scenes/colour.yaml`` at 32² super-pixels: mean normal error of the outermost ring
  2.9° → 0.67°, the mono capture's 1.3°). Masks: a site at the top count invalidates every channel
  of its block and of the blocks the interpolation reaches (one block further, as with
  ``bilinear``); dark is the channel mean's s0; a channel whose own s0 is dark is invalid for that
  channel only (its albedo).
- exposure brackets (capture format 2): each light's frames are first merged into one radiance
  mosaic in fractions of full scale at its reference exposure (:mod:`polarshape.recover.hdr`; values
  above 1 where the reference clipped); an observation is saturated when a site is clipped in every
  exposure, the mixed-block test uses each block's merged variance, and the noise model is fitted on
  the blocks read at the reference exposure. One frame per light: exactly the path without brackets.

- ``stokes`` (K, 3, H, W): linear Stokes (s0, s1, s2) in fractions of full scale (spec §1:
  s0 = ½ ΣI, s1 = I0 − I90, s2 = I45 − I135), **in each pixel's Stokes frame** (spec §1). A
  perspective capture stores angles in the sensor-plane convention; they are mapped back here.
- ``valid`` (K, H, W) bool: the observation is neither dark (s0 below ``dark_threshold`` of full
  scale: no usable polarisation, and possibly shadowed) nor saturated (any of its four sites at the
  top count: the Stokes vector is wrong), and lies in the mask.
- ``mask`` (H, W) bool object mask (the capture's mask, or every pixel lit in ≥ 3 observations).
- ``lights`` (K, H, W, 3) unit directions surface → light, camera frame, and ``irradiance``
  (K, H, W), from :meth:`polarshape.lights.Lights.illuminate` at each pixel's surface point:
  directional lights ignore where the point is (L and E are then zero-stride ``expand`` views of
  (K, 1, 1, 3) and (K, 1, 1): no memory per pixel); point lights (1/r² fall-off) need the points,
  unknown before recovery, so :func:`preprocess_capture` takes ``points`` (H, W, 3).
- ``view`` (H, W, 3) unit directions surface → camera
  (:meth:`polarshape.cameras.PerspectiveCamera.pixel_view_directions` of the super-pixel camera).

Memory: the frames are converted and demosaiced one light at a time, so beyond the outputs
preprocessing holds one frame's float64 intermediates (~0.35 GB at 2448 × 2048) and a few (K, H, W)
float64 maps; a colour capture also keeps its (K, 3, 3, H, W) per-channel Stokes in ``dtype``
(~0.36 GB at 2448 × 2048, K = 8, float32). A mono capture without calibration or brackets (Stokes at
the block centres) is worked at block resolution in counts instead (:func:`_plain_frame`): one frame's
four sites (4, H, W) and (K, H, W) maps in float32 (float64 when the black level is not a multiple of
1/256 count or ``dtype`` is float64); its Stokes vectors are the float64 estimate rounded once.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from polarshape.brdf.geometry import sensor_plane_basis, sensor_plane_stokes
from polarshape.cameras import SAMPLE_SITES, Camera, camera_from_spec
from polarshape.imaging.analyser import PolarimetricCalibration, calibrated_pinv, calibrated_stokes, ideal_equivalent_sites
from polarshape.imaging.colour import bayer_reach, colour_stokes_from_mosaic, shifted_bayer
from polarshape.imaging.demosaic import block_mean_bilinear_sites, block_mean_bilinear_stokes, stokes_from_mosaic
from polarshape.imaging.mosaic import MosaicLayout, split_mosaic
from polarshape.imaging.pixels import check_count_range, counts_to_float, max_count, reduce_mask_to_superpixels, saturation_count
from polarshape.imaging.stokes import stokes_from_four_angles
from polarshape.errors import CaptureError
from polarshape.io.capture import Capture
from polarshape.io.polarimetric import capture_polarimetric_calibration
from polarshape.recover.diagnose import check_observations, check_polarisation_signal
from polarshape.recover.edges import AlbedoEdges, find_albedo_edges
from polarshape.recover.hdr import BracketMerger, clipped_counts
from polarshape.recover.noise import demosaic_variance_factor, estimate_noise, site_redundancy
from polarshape.recover.observations import ColourInputs, RecoveryInputs

logger = logging.getLogger(__name__)

__all__ = [
    "DEMOSAIC_CHOICES", "POLARISATION_SIGNAL_MIN", "SAMPLE_SITES", "RecoveryInputs", "capture_camera",
    "colour_superpixel_stokes", "combined_colour_stokes", "mixed_superpixels", "polarisation_signal",
    "preprocess_capture", "superpixel_stokes",
]

#: How the Stokes images are estimated from the mosaic.
DEMOSAIC_CHOICES: tuple[str, ...] = ("bilinear", "superpixel")
def capture_camera(capture: Capture, sample_at: str = "centre", pixel_size_m: float | None = None) -> Camera:
    """The camera of a capture's super-pixel grid, each ray through the block's ``sample_at`` point.

    Args:
        capture: the capture (camera section of capture.yaml, frame size).
        sample_at: a key of :data:`polarshape.cameras.SAMPLE_SITES`.
        pixel_size_m: orthographic: metres per super-pixel (default 1: super-pixel units).
    """
    k, h2, w2 = capture.frames.shape
    raw = camera_from_spec(capture.spec.camera, w2, h2)
    return raw.superpixel(sample_at, pixel_size_m=1.0 if pixel_size_m is None else pixel_size_m)


def superpixel_stokes(mosaic: Tensor, layout: MosaicLayout, *, demosaic: str = "bilinear", sample_at: str = "centre") -> Tensor:
    """Stokes images (*, 3, H, W) of mosaics (*, 2H, 2W) at one point per 2×2 block (module docstring).

    Raises:
        ValueError: an unknown ``demosaic`` or ``sample_at``, or a corner site with ``"superpixel"``.
    """
    site = _check_estimate(demosaic, sample_at)
    if demosaic == "superpixel":
        return stokes_from_mosaic(mosaic, layout, "superpixel")
    if site is None:  # the mean of the block's four bilinear estimates, at block resolution
        return block_mean_bilinear_stokes(mosaic, layout)
    full = stokes_from_mosaic(mosaic, layout, "bilinear")  # (*, 3, 2H, 2W)
    return full[..., site[0]::2, site[1]::2]


def _check_estimate(demosaic: str, sample_at: str) -> tuple[int, int] | None:
    """The site of ``sample_at`` (None: the block centre), after checking both choices (:func:`superpixel_stokes`)."""
    if demosaic not in DEMOSAIC_CHOICES:
        raise ValueError(f"demosaic must be one of {DEMOSAIC_CHOICES}; got {demosaic!r}")
    if sample_at not in SAMPLE_SITES:
        raise ValueError(f"sample_at must be one of {tuple(SAMPLE_SITES)}; got {sample_at!r}")
    site = SAMPLE_SITES[sample_at]
    if demosaic == "superpixel" and site is not None:
        raise ValueError(f"sample_at {sample_at!r} needs demosaic 'bilinear' (the super-pixel estimate is at the centre)")
    return site


def colour_superpixel_stokes(mosaic: Tensor, layout: MosaicLayout, bayer: str) -> tuple[Tensor, Tensor]:
    """Per-channel and combined Stokes of colour polarisation mosaics at every block centre (module docstring).

    Args:
        mosaic: (*, 2H, 2W) raw colour mosaics, floating point (fraction of full scale); H, W ≥ 2.
        layout: polariser layout of each 2×2 block. bayer: Bayer pattern of the block grid.

    Returns:
        ``(colour, combined)``: (*, 3, 3, H, W) Stokes per channel (R, G, B; s0, s1, s2) and
        (*, 3, H, W) their channel mean (R + G + B) / 3 (:func:`combined_colour_stokes`).
    """
    colour = colour_stokes_from_mosaic(mosaic, layout, bayer, centre_sites=True)  # (*, 3, 3, H, W)
    return colour, combined_colour_stokes(colour)


def combined_colour_stokes(colour: Tensor, clean: Tensor | None = None) -> Tensor:
    """The signal normal recovery consumes: the mean of the channels (*, 3, 3, H, W) → (*, 3, H, W).

    ``clean`` (3, H, W) bool: average these channels only (each block keeps at least its own colour).
    The weights must not change from light to light: a pixel's body albedo is then their weighted
    mean of the channels' k_b, the same under every light, as the model has it.
    """
    if clean is None:
        return colour.mean(dim=-4)
    weight = clean.to(colour.dtype).unsqueeze(-3)  # (3, 1, H, W)
    return (colour * weight).sum(-4) / weight.sum(-4)


def _colour_variance_factor(layout: MosaicLayout, bayer: str) -> float:
    """:func:`polarshape.recover.noise.demosaic_variance_factor` of the combined s0, averaged over the
    four blocks of a Bayer super-block (a red block's s0 holds its own sites with weight ⅓, a green
    block's its own and its red and blue neighbours' ...): the probe sits on one block, so each
    shifted pattern puts another colour there."""
    shifts = [shifted_bayer(bayer, 2 * dx, 2 * dy) for dy in range(2) for dx in range(2)]
    return sum(demosaic_variance_factor(lambda m, b=b: colour_superpixel_stokes(m, layout, b)[1][0])
               for b in shifts) / len(shifts)


def _pixel_frame_basis(view: Tensor) -> Tensor:
    """(H, W, 2, 2) float64 basis that inverts :func:`polarshape.brdf.geometry.sensor_plane_stokes`
    (sensor-plane angles → per-pixel frames) when passed to it as ``basis``.

    The forward map sends a frame direction (cos φ, sin φ) to M (cos φ, sin φ) (then normalises);
    the inverse is the same construction with M⁻¹ (per pixel 2×2).
    """
    return torch.linalg.inv(sensor_plane_basis(view.to(torch.float64)))


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
    polarisation_check: bool = True,
    albedo_edges: bool = True,
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
        polarisation_check: refuse frames without a polarisation signal (a demosaiced or plain
            image saved as a raw mosaic; :func:`polarshape.recover.diagnose.check_polarisation_signal`).
        albedo_edges: find albedo steps (texture) from every light (:mod:`polarshape.recover.edges`): the
            blocks next to one take their own four sites' estimate, the blocks on one are left out
            (``RecoveryInputs.albedo_edges``); mono captures only.

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
    camera = capture_camera(capture, sample_at)
    view = camera.pixel_view_directions()  # (H, W, 3) float64
    # the sensor-plane angles are the per-pixel frames' when orthographic
    to_frames = _pixel_frame_basis(view) if camera.projection == "perspective" else None  # (H, W, 2, 2)
    lights, irradiance = _pixel_lights(capture, points, (h, w), dtype=dtype, device=device)
    polcal = _polcal_application(capture, demosaic=demosaic, sample_at=sample_at)
    bayer = capture.spec.camera.mosaic.bayer
    if bayer is not None and sample_at != "centre":
        raise ValueError(
            f"sample_at {sample_at!r}: a colour polarisation capture (camera.mosaic.bayer {bayer}) is estimated at the "
            "block centres only; use sample_at 'centre'"
        )
    colour_stokes = None if bayer is None else torch.empty((k, 3, 3, h, w), dtype=dtype)  # (K, colour, Stokes, H, W)
    colour_dark = None if bayer is None else torch.empty((k, 3, h, w), dtype=torch.bool)

    site = _check_estimate(demosaic, sample_at)
    brackets = BracketMerger.of(capture, dark_threshold=dark_threshold, saturation_margin=saturation_margin,
                                black_shift=None if polcal is None else polcal.black_shift)  # None: one exposure
    # One exposure of a mono sensor without calibration, Stokes at the block centres: computed at block
    # resolution in counts (_plain_frame); in float32 when that is exact (the counts and their 1/16
    # filter weights are, the black level in 1/256 counts: one rounding, at the scaling), else float64.
    plain = (bayer is None and polcal is None and brackets is None and site is None
             and frames.dtype in (np.uint8, np.uint16))
    work = torch.float32 if plain and dtype == torch.float32 and (float(black) * 256.0).is_integer() else torch.float64
    # One light at a time: the mosaic of one frame only (all K float64 frames at once are ~1.4 GB at
    # 2448 × 2048); per light only (H, W) results are kept.
    stokes = torch.empty((k, 3, h, w), dtype=work)
    dark = torch.empty((k, h, w), dtype=torch.bool)
    saturated = torch.empty((k, h, w), dtype=torch.bool)
    redundancy = torch.empty((k, h, w), dtype=work)  # the four-site check d (polarisation signal)
    scaled = torch.empty((k, h, w), dtype=work)  # d / √(s0 + c) (mixed blocks)
    block_s0 = torch.empty((k, h, w), dtype=work)  # the block's own s0 (noise model)
    reference = None if brackets is None else torch.empty((k, h, w), dtype=torch.bool)  # blocks read at the reference
    counts = torch.empty((4, h, w), dtype=work) if plain else None  # one frame's sites, in counts
    for i in range(k):
        if plain:
            s = stokes[i] if to_frames is None else torch.empty((3, h, w), dtype=work)
            top = _plain_frame(frames[i], capture.layout, counts, bilinear=demosaic == "bilinear", black=black,
                               bit_depth=bit_depth, stokes=s, block_s0=block_s0[i], redundancy=redundancy[i])
            if to_frames is not None:
                stokes[i] = sensor_plane_stokes(s.to(torch.float64), basis=to_frames)
            dark[i] = block_s0[i] < dark_threshold
            _scaled_redundancy(redundancy[i], block_s0[i], out=scaled[i])
            clipped = top >= saturation_count(bit_depth) - int(saturation_margin)  # a clipped site (clipped_counts)
            saturated[i] = _grow_saturated(clipped, demosaic)
            del s, top, clipped
            continue
        if brackets is None:
            mosaic = counts_to_float(frames[i], bit_depth, black, dtype=torch.float64)  # (2H, 2W)
        else:
            merged = brackets.merge(i)
            mosaic = merged.radiance
        if bayer is None:
            s, sites = _stokes_and_sites(mosaic, capture.layout, polcal, demosaic=demosaic, sample_at=sample_at)
        else:
            cs, s = colour_superpixel_stokes(mosaic, capture.layout, bayer)  # s: the plain mean, for dark
            sites = split_mosaic(mosaic, capture.layout)
            colour_stokes[i] = cs  # sensor-plane angles: mapped to the pixel frames once combined (below)
            colour_dark[i] = cs[:, 0] < dark_threshold
        if bayer is None:  # a colour capture's combined Stokes are made once the mask is known (below)
            stokes[i] = s if to_frames is None else sensor_plane_stokes(s, basis=to_frames)
        block_s0[i] = sites.sum(-3) * 0.5  # the block's own s0 = ½ Σ of its four sites
        # colour: a block's own s0 is one colour's, the channel mean's s0 is what recovery sees
        dark[i] = (block_s0[i] if bayer is None else s[0]) < dark_threshold
        redundancy[i] = site_redundancy(sites)
        ignore = None if polcal is None else polcal.calibration.defects
        # colour: the Bayer interpolation reaches one block further, as the bilinear demosaic does
        reach = demosaic if bayer is None else "bilinear"
        if brackets is None:
            _scaled_redundancy(redundancy[i], block_s0[i], out=scaled[i])
            saturated[i] = _saturated(frames[i], bit_depth, saturation_margin, reach, ignore=ignore)
        else:  # mixed blocks: d as a z-score of its merged variance; saturated: clipped in every exposure
            scaled[i] = merged.redundancy_z(capture.layout, redundancy[i])
            saturated[i] = _saturated_sites(merged.clipped, reach, ignore=ignore)
            reference[i] = reduce_mask_to_superpixels(merged.reference_used, "all")
            del merged
        del mosaic, s, sites
    mask = _mask(capture, ~dark & ~saturated, (h, w))
    if bayer is not None:  # at the silhouette, the channels interpolated from outside the mask leave the mean
        clean = ~bayer_reach(~mask, bayer)  # (3, H, W)
        colour_dark |= ~clean.unsqueeze(0)
        for i in range(k):
            cs = colour_stokes[i].to(torch.float64)  # (3, 3, H, W)
            s = combined_colour_stokes(cs, clean)
            stokes[i] = s if to_frames is None else sensor_plane_stokes(s, basis=to_frames)
            if to_frames is not None:
                colour_stokes[i] = sensor_plane_stokes(cs, basis=to_frames).to(dtype)
    mixed = _mixed_from_scaled(scaled, ~dark & ~saturated & mask.unsqueeze(0), n_sigma=mixed_sigma)
    del scaled, counts
    valid = ~dark & ~saturated & ~mixed & mask.unsqueeze(0)
    edges = None
    if albedo_edges and bayer is None:  # a colour capture's blocks differ in colour under every light: no test
        edges = find_albedo_edges(block_s0, ~dark & ~saturated & mask.unsqueeze(0))
        _superpixel_next_to_edges(stokes, edges, mask, frames, capture, polcal, brackets, to_frames, demosaic=demosaic)
        valid &= ~edges.on_edge.unsqueeze(0)
    if polcal is not None:  # blocks with too few good sites (≥ 2 defects) carry no Stokes vector
        valid &= polcal.valid.unsqueeze(0)
    # σ of s0 from quantisation (1 count / √12 per site, ½Σ of 4 sites) plus a read-noise floor.
    step = 1.0 / (max_count(bit_depth) - black)
    noise_std = float(step / np.sqrt(12.0))
    has_pol = _has_polarisation(stokes, redundancy, valid, step)
    if bayer is None:
        factor = demosaic_variance_factor(lambda m: superpixel_stokes(m, capture.layout, demosaic=demosaic, sample_at=sample_at)[0])
    else:
        factor = _colour_variance_factor(capture.layout, bayer)
    # with brackets: the reference exposure's noise (recover/hdr.py: what the noise model sees)
    noise_usable = valid if reference is None else valid & reference
    noise = estimate_noise(redundancy, block_s0, noise_usable, step=step, variance_factor=factor)
    del redundancy, block_s0
    out = RecoveryInputs(
        stokes=stokes.to(device=device, dtype=dtype),
        valid=valid.to(device),
        saturated=saturated.to(device),
        mask=mask.to(device),
        lights=lights,
        irradiance=irradiance,
        view=view.to(device=device, dtype=dtype),
        noise_std=noise_std,
        has_polarisation=has_pol,
        noise=noise,
        colour=None if bayer is None else ColourInputs(
            stokes=colour_stokes.to(device), valid=(valid.unsqueeze(1) & ~colour_dark).to(device), bayer=bayer),
        albedo_edges=None if edges is None else (edges.on_edge & mask).to(device),
    )
    del stokes
    if logger.isEnabledFor(logging.DEBUG):  # (counting 10⁷ observations is not free)
        logger.debug("preprocess: K=%d, %dx%d super-pixels, %d in mask, %d valid observations", k, h, w,
                     int(torch.count_nonzero(mask)), int(torch.count_nonzero(valid)))
    check_observations(capture, out, dark=dark, saturated=saturated, dark_threshold=dark_threshold,
                       saturation_margin=saturation_margin, points=points)
    if polarisation_check:
        check_polarisation_signal(capture, out, bilinear_centre=(demosaic == "bilinear" and sample_at == "centre"
                                                                 and bayer is None and polcal is None))
    return out


@dataclass(frozen=True)
class _PolcalApplication:
    """A capture's polarimetric calibration, ready for every frame: the per-pixel black-level
    correction, and the pseudo-inverses of the block (and, for ``demosaic: bilinear``, per-pixel)
    analysis matrices (:func:`polarshape.imaging.analyser.calibrated_pinv`)."""

    calibration: PolarimetricCalibration
    black_shift: Tensor  # (2H, 2W) (black − nominal black) / (max count − nominal black)
    block: tuple[Tensor, Tensor]  # superpixel P (H, W, 3, 4), valid (H, W)
    full: tuple[Tensor, Tensor] | None  # bilinear P (2H, 2W, 3, 4), valid (2H, 2W)
    valid: Tensor  # (H, W) blocks with a Stokes vector


def _polcal_application(capture: Capture, *, demosaic: str, sample_at: str) -> _PolcalApplication | None:
    """Read ``camera.polarimetric_calibration`` (None without one) and prepare it for the frames."""
    calibration = capture_polarimetric_calibration(capture)
    if calibration is None:
        return None
    if capture.spec.camera.mosaic.bayer is not None:
        raise CaptureError(
            "camera.polarimetric_calibration in capture.yaml: a calibration of a colour polarisation sensor "
            "(camera.mosaic.bayer) is not supported yet; remove the field"
        )
    if demosaic not in DEMOSAIC_CHOICES:
        raise ValueError(f"demosaic must be one of {DEMOSAIC_CHOICES}; got {demosaic!r}")
    try:
        block = calibrated_pinv(calibration, capture.layout, method="superpixel")
        # a calibrated bilinear estimate: every angle class and its rows interpolated to every pixel
        full = calibrated_pinv(calibration, capture.layout, method="bilinear") if demosaic == "bilinear" else None
    except ValueError as err:
        raise CaptureError(f"camera.polarimetric_calibration in capture.yaml: {err}") from None
    valid = block[1]
    if full is not None:
        site = SAMPLE_SITES[sample_at]
        ok = full[1]
        ok = ok.reshape(ok.shape[0] // 2, 2, ok.shape[1] // 2, 2).all(3).all(1) if site is None else ok[site[0]::2, site[1]::2]
        valid = valid & ok
    nominal = capture.spec.camera.black_level
    shift = (calibration.black_level - nominal) / (max_count(capture.bit_depth) - nominal)
    logger.info(
        "preprocess: polarimetric calibration %s (%d defective pixels, %d blocks without a Stokes vector; %s estimate)",
        capture.spec.camera.polarimetric_calibration, int(calibration.defects.sum()), int((~valid).sum()),
        "per-pixel bilinear" if full is not None else "block",
    )
    return _PolcalApplication(calibration=calibration, black_shift=shift, block=block, full=full, valid=valid)


def _stokes_and_sites(mosaic: Tensor, layout: MosaicLayout, polcal: _PolcalApplication | None, *, demosaic: str,
                      sample_at: str) -> tuple[Tensor, Tensor]:
    """Stokes (3, H, W) of a mosaic (2H, 2W) at ``sample_at`` and its sites (4, H, W) at 0°, 45°, 90°, 135°.

    With a calibration the mosaic (black-corrected with the nominal black level) first takes the
    per-pixel black level, then each block's (or pixel's) own analysis matrix gives ``s``; the sites
    are those ideal analysers would have seen (:func:`polarshape.imaging.analyser.ideal_equivalent_sites`),
    so that the four-site checks (dark, mixed, noise model) see noise and not the sensor's PRNU.
    """
    if polcal is None:
        return superpixel_stokes(mosaic, layout, demosaic=demosaic, sample_at=sample_at), split_mosaic(mosaic, layout)
    mosaic = mosaic - polcal.black_shift.to(mosaic)
    cal = polcal.calibration
    sites = ideal_equivalent_sites(mosaic, cal, layout, pinv=polcal.block)
    if polcal.full is None:
        return calibrated_stokes(mosaic, cal, layout, pinv=polcal.block)[0], sites
    full = calibrated_stokes(mosaic, cal, layout, method="bilinear", pinv=polcal.full)[0]  # (3, 2H, 2W)
    site = SAMPLE_SITES[sample_at]
    if site is None:
        return F.avg_pool2d(full.unsqueeze(1), 2).squeeze(1), sites
    return full[..., site[0]::2, site[1]::2], sites


def _plain_frame(frame: np.ndarray, layout: MosaicLayout, counts: Tensor, *, bilinear: bool, black: float, bit_depth: int,
                 stokes: Tensor, block_s0: Tensor, redundancy: Tensor) -> Tensor:
    """One exposure of a mono sensor without calibration, at block resolution and in counts.

    The frame (2H, 2W) integer counts is split into its four sites ``counts`` (4, H, W) (a work
    buffer, overwritten); from them the block's own s0 and the four-site d (fractions of full scale)
    go into ``block_s0`` and ``redundancy`` (H, W), and the Stokes vector at the block centre
    (``bilinear``: :func:`polarshape.imaging.demosaic.block_mean_bilinear_sites`, else the plain
    2×2 estimate) into ``stokes`` (3, H, W) — what :func:`counts_to_float` followed by
    :func:`superpixel_stokes` and :func:`split_mosaic` give, with the black level and the scale
    applied once at the end (both estimates are linear, and s0's weights sum to 2 per black level).

    Returns:
        (H, W) the largest count of each block (saturation).

    Raises:
        ValueError: a count above the bit depth's top (as :func:`counts_to_float`).
    """
    full = float(max_count(bit_depth) - black)
    sites = counts.numpy()
    for c in range(4):
        i, j = layout.site_of_channel(c)
        sites[c] = frame[i::2, j::2]  # exact: counts of ≤ 16 bits in float32
    top = counts.amax(0)  # (H, W)
    hi = int(top.max()) if top.numel() else 0
    if hi > max_count(bit_depth):
        check_count_range(int(frame.min()), hi, bit_depth)
    torch.sum(counts, 0, out=block_s0).sub_(4.0 * black).div_(2.0 * full)  # ½ Σ (I − black) / full
    torch.div(site_redundancy(counts), full, out=redundancy)  # the black level cancels in d
    intensities = block_mean_bilinear_sites(counts, layout, inplace=True) if bilinear else counts
    stokes_from_four_angles(intensities, out=stokes)  # (3, H, W) in counts: exact
    stokes[0].sub_(2.0 * black)
    stokes.div_(full)  # the one rounding
    return top


def _saturated(frames: np.ndarray, bit_depth: int, margin: int, demosaic: str, *, ignore: Tensor | None = None) -> Tensor:
    """(*, H, W) bool observations of frames (*, 2H, 2W) with a site at the top count (less ``margin``);
    ``ignore`` (2H, 2W): pixels that do not count (a calibration's defects: a hot pixel stuck at the top)."""
    return _saturated_sites(clipped_counts(frames, bit_depth, margin), demosaic, ignore=ignore)


def _saturated_sites(clipped: Tensor, demosaic: str, *, ignore: Tensor | None = None) -> Tensor:
    """(*, H, W) bool observations with a ``clipped`` (*, 2H, 2W) site (:func:`_saturated`)."""
    if ignore is not None:
        clipped = clipped & ~ignore
    return _grow_saturated(reduce_mask_to_superpixels(clipped, "any"), demosaic)  # (*, H, W)


def _grow_saturated(saturated: Tensor, demosaic: str) -> Tensor:
    """(*, H, W) bool blocks with a clipped site → the observations they spoil: with ``bilinear`` the
    interpolation reaches one block further, so does a clipped site (its 3×3 neighbourhood)."""
    if demosaic != "bilinear":
        return saturated
    grown = saturated.clone()
    grown[..., :, 1:] |= saturated[..., :, :-1]
    grown[..., :, :-1] |= saturated[..., :, 1:]
    rows = grown.clone()
    grown[..., 1:, :] |= rows[..., :-1, :]
    grown[..., :-1, :] |= rows[..., 1:, :]
    return grown


def _mask(capture: Capture, usable: Tensor, shape: tuple[int, int]) -> Tensor:
    """(H, W) bool: the capture's mask, else every pixel with ≥ 3 usable (K, H, W) observations."""
    if capture.mask is not None:
        mask = torch.from_numpy(np.asarray(capture.mask, dtype=bool))
        if tuple(mask.shape) != shape:
            raise ValueError(f"capture mask has shape {tuple(mask.shape)}; expected the super-pixel shape {shape}")
        return mask
    mask = usable.sum(0, dtype=torch.int16) >= 3  # (int16: a bool sum into int64 is ~10× slower)
    logger.info("capture has no mask: using the %d pixels lit in ≥ 3 observations", int(torch.count_nonzero(mask)))
    return mask


def _has_polarisation(stokes: Tensor, redundancy: Tensor, valid: Tensor, step: float) -> bool:
    """Whether s1, s2 of ``stokes`` (K, 3, H, W) hold a signal: above the quantisation ``step``, and
    coherent beyond the four-site noise (:func:`polarisation_signal`; ``redundancy`` (K, H, W) its d).
    One light at a time (no (K, 2, H, W) temporaries)."""
    top = max(float(torch.maximum(stokes[i, 1].abs(), stokes[i, 2].abs()).masked_fill_(~valid[i], 0.0).amax())
              for i in range(stokes.shape[0]))
    if not top > 4 * step:  # (|s1|, |s2| ≥ 0: 0 without valid observations)
        return False
    num, den = 0.0, 0.0
    for i in range(stokes.shape[0]):
        n_i, d_i = _pair_sums(stokes[i, 1:], redundancy[i].square(), valid[i])
        num, den = num + n_i, den + d_i
    signal = _signal_ratio(num, den)
    logger.debug("preprocess: polarisation signal %.3g (threshold %.2g)", signal, POLARISATION_SIGNAL_MIN)
    return signal >= POLARISATION_SIGNAL_MIN


def _pixel_lights(capture: Capture, points: np.ndarray | None, shape: tuple[int, int], *, dtype: torch.dtype,
                  device: torch.device | str) -> tuple[Tensor, Tensor]:
    """L (K, H, W, 3) and E (K, H, W) of the capture's lights at the surface ``points``, in ``dtype``.

    Directional lights only: the same L and E at every pixel, returned as zero-stride views
    (``expand``) of (K, 1, 1, 3) and (K, 1, 1) tensors — no (K, H, W, 3) array is made.
    """
    lights = capture.lights()
    if points is None and lights.has_point_lights:
        raise ValueError(
            "capture.yaml has point lights (position): pass points=(H, W, 3) surface points (metres, "
            "camera frame; e.g. from a depth estimate) to preprocess_capture, or calibrate directional lights"
        )
    if points is not None:
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape != (*shape, 3):
            raise ValueError(f"points must have shape (H, W, 3) = {(*shape, 3)}; got {pts.shape}")
    if not lights.has_point_lights:  # directional lights do not depend on where the surface is
        l_dir, e_dir = lights.illuminate(torch.zeros(1, 1, 3, dtype=torch.float64))  # (K, 1, 1, 3), (K, 1, 1)
        l_dir, e_dir = l_dir.to(device=device, dtype=dtype), e_dir.to(device=device, dtype=dtype)
        k = l_dir.shape[0]
        return l_dir.expand(k, *shape, 3), e_dir.expand(k, *shape)
    l_pix, e_pix = lights.illuminate(torch.from_numpy(pts))
    return l_pix.to(device=device, dtype=dtype), e_pix.to(device=device, dtype=dtype)


def _scaled_redundancy(d: Tensor, s0: Tensor, *, out: Tensor | None = None) -> Tensor:
    """(*, H, W) d / √(s0 + c), c = 10⁻³, of the blocks' d and own s0 (*, H, W) (see
    :func:`mixed_superpixels`); into ``out`` when given."""
    den = torch.clamp_min(s0, 0.0, out=out).add_(1e-3).sqrt_()
    return torch.div(d, den, out=den)


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
    return _signal_ratio(*_pair_sums(linear, site_redundancy(sites).square(), valid))


def _pair_sums(linear: Tensor, d2: Tensor, valid: Tensor) -> tuple[float, float]:
    """Numerator and denominator of :func:`polarisation_signal`: linear (*, 2, H, W), d² (*, H, W),
    valid (*, H, W); sums over any leading dimensions (one light at a time adds up to all K)."""
    num, den = 0.0, 0.0
    for dim in (-1, -2):
        n = linear.shape[dim]
        if n < 3:
            continue
        off = ~(valid.narrow(dim, 0, n - 2) & valid.narrow(dim, 2, n - 2))  # not a valid pair
        a, b = linear.narrow(dim, 0, n - 2), linear.narrow(dim, 2, n - 2)
        num += float((a * b).sum(-3).masked_fill_(off, 0.0).sum(dtype=torch.float64))
        den += 0.5 * float((d2.narrow(dim, 0, n - 2) + d2.narrow(dim, 2, n - 2)).masked_fill_(off, 0.0)
                           .sum(dtype=torch.float64))
    return num, den


def _selected(x: Tensor, where: Tensor) -> Tensor:
    """``x[where]`` (N,) for bool ``where`` of x's shape; on the CPU through numpy (several times
    faster than torch's boolean indexing of millions of elements)."""
    if x.device.type == "cpu":
        return torch.from_numpy(x.numpy()[where.numpy()])
    return x[where]


def _lower_median(v: Tensor) -> float:
    """``float(v.median())`` of a 1-D tensor (the lower of the two middle values for an even count),
    on the CPU by a numpy partition (O(N), several times faster than torch's median)."""
    if v.device.type == "cpu":
        k = (v.numel() - 1) // 2
        return float(np.partition(v.numpy(), k)[k])
    return float(v.median())


def _signal_ratio(num: float, den: float) -> float:
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
    return _mixed_from_scaled(_scaled_redundancy(site_redundancy(sites), 0.5 * sites.sum(-3)), usable, n_sigma=n_sigma)


def _mixed_from_scaled(d: Tensor, usable: Tensor, *, n_sigma: float | None) -> Tensor:
    """:func:`mixed_superpixels` from d / √(s0 + c) (K, H, W) (:func:`_scaled_redundancy`)."""
    if n_sigma is None:
        return torch.zeros_like(usable)
    v = _selected(d, usable)
    if v.numel() < 16:
        return torch.zeros_like(usable)
    sigma = _lower_median((v - _lower_median(v)).abs_()) * 1.4826
    if sigma <= 0:
        return torch.zeros_like(usable)
    mixed = d.abs() > n_sigma * sigma
    if logger.isEnabledFor(logging.DEBUG):
        logger.debug("mixed super-pixel observations: %d of %d usable", int(torch.count_nonzero(mixed & usable)),
                     int(torch.count_nonzero(usable)))
    return mixed


# --- albedo edges (polarshape.recover.edges) ----------------------------------------------------


def _superpixel_next_to_edges(stokes: Tensor, edges: AlbedoEdges, mask: Tensor, frames: np.ndarray, capture: Capture,
                              polcal: _PolcalApplication | None, brackets: BracketMerger | None,
                              to_frames: Tensor | None, *, demosaic: str) -> None:
    """Replace in place the bilinear Stokes (K, 3, H, W) of the ``mask`` blocks next to an albedo step (and not
    on it) with the block's own four-site estimate: the interpolation from the other side is a false polarisation.
    The frames are read again only when there is such a block, and without a calibration only at those blocks
    (:func:`_blocks_side_by_side`: the super-pixel estimate of a block is its own four sites')."""
    swap = edges.adjacent & ~edges.on_edge & mask  # (H, W)
    if demosaic != "bilinear" or not bool(swap.any()):
        return
    ys, xs = torch.nonzero(swap.cpu(), as_tuple=True)  # (N,) each
    basis = None if to_frames is None else to_frames[ys, xs].unsqueeze(0)  # (1, N, 2, 2)
    for i in range(stokes.shape[0]):
        if polcal is not None:  # per-pixel black level and analysers: the whole frame, as preprocessing read it
            mosaic = counts_to_float(frames[i], capture.bit_depth, capture.spec.camera.black_level, dtype=torch.float64)
            s, _ = _stokes_and_sites(mosaic, capture.layout, polcal, demosaic="superpixel", sample_at="centre")
            if to_frames is not None:
                s = sensor_plane_stokes(s, basis=to_frames)
            stokes[i] = torch.where(swap, s, stokes[i])
            continue
        if brackets is None:  # the blocks' counts only, converted as the whole frame would be
            mosaic = counts_to_float(_blocks_side_by_side(frames[i], ys, xs), capture.bit_depth,
                                     capture.spec.camera.black_level, dtype=torch.float64)  # (2, 2N)
        else:
            mosaic = _blocks_side_by_side(brackets.merge(i).radiance, ys, xs)
        s = superpixel_stokes(mosaic, capture.layout, demosaic="superpixel")  # (3, 1, N)
        if basis is not None:
            s = sensor_plane_stokes(s, basis=basis)
        stokes[i, :, ys, xs] = s[:, 0].to(stokes.dtype)
    logger.debug("albedo edges: %d blocks next to a step (own-site estimate), %d on one (left out)",
                 int(swap.sum()), int(edges.on_edge.sum()))


def _blocks_side_by_side(mosaic: np.ndarray | Tensor, ys: Tensor, xs: Tensor) -> np.ndarray | Tensor:
    """The 2×2 blocks (ys, xs) (N,) of a mosaic (2H, 2W) as one (2, 2N) mosaic, block n at columns 2n, 2n + 1
    (the layout of every block unchanged)."""
    h, w = mosaic.shape[0] // 2, mosaic.shape[1] // 2
    if isinstance(mosaic, Tensor):
        blocks = mosaic.reshape(h, 2, w, 2)[ys.to(mosaic.device), :, xs.to(mosaic.device)]  # (N, 2, 2)
        return blocks.permute(1, 0, 2).reshape(2, -1)
    blocks = mosaic.reshape(h, 2, w, 2)[ys.numpy(), :, xs.numpy()]  # (N, 2, 2)
    return np.ascontiguousarray(blocks.transpose(1, 0, 2)).reshape(2, -1)
