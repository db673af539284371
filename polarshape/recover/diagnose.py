"""Whether a capture can be recovered at all, and what in it looks wrong: :func:`check_observations`,
called once by :func:`polarshape.recover.preprocess.preprocess_capture`, decided from the counts the
camera delivered (never from a fit that would have to invent an answer first).

Refused with a :class:`~polarshape.errors.CaptureError` that names the cause and the fix:

- a light behind the object seen from the camera (a point light at or beyond the surface's median
  depth, a direction pointing away from the camera);
- no usable observations: no mask pixel has :data:`~polarshape.recover.priors.MIN_OBSERVATIONS`
  lit, unsaturated views — every frame dark, dark because of ``camera.black_level``, every
  observation saturated, saturated because of the saturation margin, or a mix;
- frames that do not change with the light (s0 the same in every light to a few quantisation steps
  at every pixel: one frame written K times, a light rig that did not switch).

Refused by :func:`check_polarisation_signal` (run by ``polarshape run`` after preprocessing unless
``preprocess.polarisation_check: false``):

- frames without the polarisation a raw mosaic of an object always carries: a single demosaiced
  polariser image (or a plain intensity image) saved as a frame is read as a mosaic whose four
  sites are four neighbouring pixels of one smooth image, and the 2×2 estimate turns the image's
  gradient into a made-up polarisation (a user measured a DoLP of 0.0006 and an AoLP 100° off).
  The bilinear demosaic is exact on linear intensity fields, so such frames have almost no
  bilinear s1, s2, whereas an object's diffuse and specular polarisation survive it:
  :func:`polarisation_dolp` is a high percentile of the DoLP of the bilinear Stokes vectors,
  averaged over small windows of usable observations (the noise averages out, the signal does
  not). Plain intensity frames stored as four equal sites (``polarshape import diligent``) have
  DoLP exactly 0 by design and pass.

Warned (:class:`~polarshape.errors.SuspiciousInputWarning`; the run goes on):

- two lights at one place (directions < 0.5° apart, positions < 1 mm apart), two bit-identical frames;
- the brightest count below 1/16 of full scale (low-bit data declared at a higher ``bit_depth``,
  or an exposure far too short): a :class:`~polarshape.errors.BitDepthWarning`.
"""

from __future__ import annotations

import logging
import math
import warnings

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from polarshape.errors import BitDepthWarning, CaptureError, SuspiciousInputWarning
from polarshape.imaging.demosaic import stokes_from_mosaic
from polarshape.imaging.pixels import counts_to_float, max_count, reduce_mask_to_superpixels, saturation_count
from polarshape.io.capture import Capture
from polarshape.lights import DirectionalLight, PointLight
from polarshape.recover.observations import RecoveryInputs
from polarshape.recover.priors import MIN_OBSERVATIONS

logger = logging.getLogger(__name__)

__all__ = ["CONSTANT_STEPS", "DUPLICATE_ANGLE_DEG", "DUPLICATE_DISTANCE_M", "LOW_SIGNAL_FRACTION",
           "POLARISATION_DOLP_MIN", "POLARISATION_LIT_FRACTION", "POLARISATION_MIN_OBSERVATIONS",
           "POLARISATION_PERCENTILE", "POLARISATION_WINDOW", "check_observations", "check_polarisation_signal",
           "dark_capture_cause", "is_plain_intensity", "polarisation_dolp"]

#: A pixel whose s0 spreads over at most this many quantisation steps across its usable
#: observations does not change with the light; every pixel so: the capture is refused.
CONSTANT_STEPS = 4
#: Directional lights closer than this (degrees) light the object from one direction.
DUPLICATE_ANGLE_DEG = 0.5
#: Point lights closer than this (metres) are one light.
DUPLICATE_DISTANCE_M = 1e-3
#: The brightest count below this fraction of full scale (bit depths above 8): a warning.
LOW_SIGNAL_FRACTION = 1.0 / 16.0
#: Every this many-th count of a frame is compared first when looking for bit-identical frames.
_IDENTITY_SAMPLE_STRIDE = 97

#: :func:`polarisation_dolp` below this: the frames carry no polarisation signal (refused). Measured
#: (``python benchmarks/polarisation_check.py``; 99th percentile, 5×5 windows, lit observations):
#: raw mosaics of simulated polarising spheres (64 and 128 px, three FMBRDF materials, with and
#: without noise) 0.023 (IOR 1.3, k_s 0.3, no noise) to 0.122, official_sphere128 0.144,
#: mitsuba_sphere_a020 0.209; the same captures with every frame replaced by one polariser image
#: upsampled ×2 (OpenCV bilinear) 0.0001–0.0002, by s0 / 2 of the bilinear demosaic 0.0004–0.0033.
#: Not caught: the full-resolution bilinear demosaic of one polariser (its interpolation pattern
#: aliases the image's curvature into s1, s2: 0.0033 on mitsuba_sphere_a020, 0.0124 on
#: official_sphere128, 0.009–0.020 on 32–64-pixel spheres), and noisy simulated unpolarised
#: (Lambertian) spheres, 0.020–0.023 (noise-free at 128 px: 0.004, refused).
POLARISATION_DOLP_MIN = 0.01
#: Side (super-pixels) of the windows the Stokes vectors are averaged over before the DoLP.
POLARISATION_WINDOW = 5
#: The percentile of the windowed DoLP over the usable object observations of all frames.
POLARISATION_PERCENTILE = 99.0
#: Observations with s0 below this fraction of their frame's 99th-percentile s0 are left out (noise).
POLARISATION_LIT_FRACTION = 0.2
#: Fewer usable observations than this: too little to judge; the check passes.
POLARISATION_MIN_OBSERVATIONS = 64


def check_observations(
    capture: Capture,
    inputs: RecoveryInputs,
    *,
    dark: Tensor,
    saturated: Tensor,
    dark_threshold: float,
    saturation_margin: int,
    points: np.ndarray | None = None,
) -> None:
    """Refuse a capture recovery cannot use, warn about one that looks wrong (module docstring).

    Args:
        capture: the capture (frames (K, 2H, 2W) counts, capture.yaml).
        inputs: its preprocessed tensors (``valid`` (K, H, W), ``mask`` (H, W), ``stokes`` (K, 3, H, W)).
        dark, saturated: (K, H, W) bool observations below ``dark_threshold`` / with a site at the
            top count less ``saturation_margin`` (as preprocessing found them).
        dark_threshold: fraction of full scale below which an observation is dark.
        saturation_margin: counts below the top still treated as saturated.
        points: (H, W, 3) surface points (metres, camera frame), when preprocessing had them.

    Raises:
        CaptureError: a light behind the object, no usable observations, frames that do not change
            with the light.
    """
    mask = inputs.mask.cpu()
    region = mask if bool(mask.any()) else torch.ones_like(mask)  # (H, W): where the object is
    _check_lights_in_front(capture, region, points)
    _check_usable(capture, inputs.valid.cpu(), region, dark.cpu(), saturated.cpu(), dark_threshold, saturation_margin)
    _check_light_changes(capture, inputs)
    for message in (*_coincident_lights(capture), *_identical_frames(capture)):
        warnings.warn(SuspiciousInputWarning(message), stacklevel=2)
    for message in _low_counts(capture):  # a named kind: the self-checks list it (polarshape.recover.selfcheck)
        warnings.warn(BitDepthWarning(message), stacklevel=2)


def _check_lights_in_front(capture: Capture, region: Tensor, points: np.ndarray | None) -> None:
    """No light may sit behind the object: point lights at or beyond the median depth of the
    surface ``points`` (when given), directions with z > 0."""
    lights = capture.lights()
    depth = math.inf
    if points is not None and lights.has_point_lights:
        z = np.asarray(points, dtype=np.float64)[..., 2][region.numpy()]
        z = z[np.isfinite(z)]
        if z.size:
            depth = float(np.median(z))
    bad = lights.behind(depth)
    if not bad:
        return
    lines = []
    for k in bad:
        light = lights[k]
        if isinstance(light, PointLight):
            lines.append(f"lights[{k}].position z = {light.position[2]:.6g} m is at or beyond the surface's median "
                         f"depth {depth:.6g} m")
        else:
            assert isinstance(light, DirectionalLight)
            lines.append(f"lights[{k}].direction z = {light.direction[2]:.6g} > 0 points away from the camera")
    raise CaptureError(
        f"capture.yaml: {'; '.join(lines)}: behind the object seen from the camera: z is forward, away from the "
        "camera (camera frame: x right, y down), so a light on the camera side has a smaller z than the surface "
        "(a direction z < 0); flip the sign of z if your convention has +z toward the camera, or give the surface "
        "depth (polarshape run: integration.reference_depth_m)"
    )


def _region_counts(frames: np.ndarray, region: Tensor) -> np.ndarray:
    """(K, N) counts of the sites of the ``region`` (H, W) super-pixels."""
    sites = np.repeat(np.repeat(region.numpy(), 2, axis=0), 2, axis=1)  # (2H, 2W)
    return frames[:, sites]


def dark_capture_cause(capture: Capture, brightest: int, threshold: float, threshold_name: str) -> str:
    """Why a capture whose every observation is dark is so: its black level, or dark frames.

    Args:
        capture: the capture (``camera.bit_depth``, ``camera.black_level``).
        brightest: its brightest count (where the object is).
        threshold: the fraction of full scale below which an observation is dark, and
            ``threshold_name`` the key that sets it (named in the message).
    """
    camera = capture.spec.camera
    bits, black = camera.bit_depth, float(camera.black_level)
    full = max_count(bits)
    if black > 0 and brightest <= black:
        return (f"every count is at or below camera.black_level {black:g} (the brightest is {brightest}): black_level is "
                f"in counts of the declared bit_depth {bits} (full scale {full}); lower it")
    if black > 0 and brightest >= threshold * full:
        return (f"camera.black_level {black:g} leaves the brightest count {brightest} below {threshold_name} "
                f"{threshold:g} of full scale: black_level is in counts of the declared bit_depth {bits} "
                f"(full scale {full}); lower it")
    return (f"all frames are dark: the brightest count is {brightest} of full scale {full} (observations below "
            f"{threshold_name} {threshold:g} of full scale are dark) — lights off, lens cap, exposure too short?")


def _check_usable(capture: Capture, valid: Tensor, region: Tensor, dark: Tensor, saturated: Tensor,
                  dark_threshold: float, margin: int) -> None:
    """At least one pixel of the ``region`` needs :data:`MIN_OBSERVATIONS` ``valid`` (K, H, W)
    observations; otherwise the cause is read from the counts and named."""
    k = valid.shape[0]
    if k < MIN_OBSERVATIONS:
        return  # too few lights: recovery refuses the capture itself, naming the fix
    if bool(((valid.sum(0, dtype=torch.int16) >= MIN_OBSERVATIONS) & region).any()):  # (int16: ~10× a bool→int64 sum)
        return
    obs = region.unsqueeze(0).expand_as(valid)  # (K, H, W)
    n = int(obs.sum())
    n_sat = int((saturated & obs).sum())
    n_dark = int((dark & ~saturated & obs).sum())
    bits = capture.spec.camera.bit_depth
    counts = _region_counts(capture.frames, region)  # (K, N)
    hi = int(counts.max()) if counts.size else 0
    if n_dark == n:
        cause = dark_capture_cause(capture, hi, dark_threshold, "preprocess.dark_threshold")
    elif n_sat == n:
        top = saturation_count(bits)
        clipped = reduce_mask_to_superpixels(torch.from_numpy(capture.frames >= top), "any")  # (K, H, W) at margin 0
        if margin > 0 and not bool(clipped[obs].all()):
            cause = (f"preprocess.saturation_margin_counts {margin} leaves no count below the saturation level "
                     f"{top - margin} (top count {top}): lower it")
        else:
            cause = f"every observation is saturated (a site at the top count {top}): shorten the exposure"
    elif n_dark + n_sat == n:
        all_dark = [i for i in range(k) if bool((dark[i] | ~region).all())]
        all_sat = [i for i in range(k) if bool((saturated[i] | ~region).all())]
        cause = (f"every observation is dark ({n_dark} of {n}; wholly dark: lights {_listed(all_dark)}) or saturated "
                 f"({n_sat} of {n}; wholly saturated: lights {_listed(all_sat)}): one exposure suits none of the lights "
                 "— check the lights' intensities and the exposure")
    else:
        cause = (f"of {n} observations {n_dark} are dark, {n_sat} saturated and the other {n - n_dark - n_sat} too few "
                 f"per pixel or straddling an edge: every pixel needs {MIN_OBSERVATIONS} lights that reach it unsaturated "
                 "— check the lights and the exposure")
    raise CaptureError(f"capture: no usable observations (no mask pixel has {MIN_OBSERVATIONS} lit, unsaturated "
                       f"views): {cause}")


def _listed(indices: list[int]) -> str:
    return ", ".join(map(str, indices)) if indices else "none"


def _check_light_changes(capture: Capture, inputs: RecoveryInputs) -> None:
    """Refuse frames whose s0 does not change with the light: at every pixel with ≥ 2 usable
    observations, max_k s0 − min_k s0 ≤ :data:`CONSTANT_STEPS` quantisation steps."""
    k = inputs.num_lights
    if k < 2:
        return
    s0 = inputs.stokes[:, 0]  # (K, H, W)
    valid = inputs.valid & inputs.mask.unsqueeze(0)
    top = torch.full(inputs.shape, -math.inf, dtype=s0.dtype, device=s0.device)
    low = torch.full(inputs.shape, math.inf, dtype=s0.dtype, device=s0.device)
    for i in range(k):  # running extremes: no (K, H, W) copies
        top = torch.where(valid[i], torch.maximum(top, s0[i]), top)
        low = torch.where(valid[i], torch.minimum(low, s0[i]), low)
    pixels = valid.sum(0, dtype=torch.int16) >= 2
    if not bool(pixels.any()):
        return
    camera = capture.spec.camera
    step = 1.0 / (max_count(camera.bit_depth) - float(camera.black_level))  # one count, fraction of full scale
    spread = float((top - low)[pixels].max()) / step
    logger.debug("diagnose: largest s0 change across the lights %.1f quantisation steps", spread)
    if spread <= CONSTANT_STEPS:
        raise CaptureError(
            f"capture: the frames do not change with the light: at each of the {int(pixels.sum())} mask pixels, s0 "
            f"differs across the {k} lights by at most {spread:.1f} quantisation steps (≤ {CONSTANT_STEPS}) — the "
            f"same frame written {k} times? light rig not switching? Check lights[*].frame in capture.yaml and the rig"
        )


def _coincident_lights(capture: Capture) -> list[str]:
    lights = capture.lights()
    frames = [light.frame for light in capture.spec.lights]
    out = []
    for i, j, sep in lights.coincident(DUPLICATE_ANGLE_DEG, DUPLICATE_DISTANCE_M):
        what = (f"the same direction ({sep:.2f}° apart)" if isinstance(lights[i], DirectionalLight)
                else f"the same position ({1000 * sep:.2f} mm apart)")
        out.append(f"capture.yaml lights[{i}], lights[{j}]: lights {i} and {j} ({frames[i]}, {frames[j]}) have {what}: "
                   "the second adds no shape information — a copied entry?")
    return out


def _identical_frames(capture: Capture) -> list[str]:
    # a sparse sample tells distinct frames apart (noise alone does); frames whose samples agree are
    # compared whole (a hash of every byte of every frame cost more than all the other checks)
    groups: list[list[int]] = []
    samples: list[bytes] = []
    for k, frame in enumerate(capture.frames):
        sample = np.ascontiguousarray(frame).reshape(-1)[::_IDENTITY_SAMPLE_STRIDE].tobytes()
        for same, seen in zip(groups, samples):
            if seen == sample and np.array_equal(capture.frames[same[0]], frame):
                same.append(k)
                break
        else:
            groups.append([k])
            samples.append(sample)
    names = [light.frame for light in capture.spec.lights]
    out = []
    for same in groups:
        if len(same) > 1:
            listed = ", ".join(f"lights[{k}].frame {names[k]}" for k in same)
            frame = capture.frames[same[0]]
            lo, hi = int(frame.min()), int(frame.max())
            hint = (f"every count is {lo}: lights that did not fire, a lens cap?" if lo == hi
                    else "the same image saved under several lights? Check the frame files and the light rig")
            out.append(f"capture.yaml {listed}: {len(same)} frames are bit-identical — {hint}")
    return out


def _low_counts(capture: Capture) -> list[str]:
    bits = capture.bit_depth
    full = max_count(bits)
    hi = int(capture.frames.max()) if capture.frames.size else 0
    if bits > 8 and hi < LOW_SIGNAL_FRACTION * full:
        return [f"camera.bit_depth: the brightest count {hi} is below 1/16 of full scale {full}: "
                f"{max(hi.bit_length(), 1)}-bit data declared bit_depth {bits}? or exposure far too short"]
    return []


# --- polarisation signal -------------------------------------------------------------------------


def is_plain_intensity(capture: Capture, region: np.ndarray | None = None) -> bool:
    """Whether every super-pixel of ``region`` (H, W) bool (default: all) holds four equal sites
    in every frame: plain intensity data stored on purpose (``polarshape import diligent``)."""
    for f in capture.frames:  # (2H, 2W): one frame at a time, the first unequal block decides (a real mosaic)
        sites = (f[0::2, 0::2], f[0::2, 1::2], f[1::2, 0::2], f[1::2, 1::2])  # (H, W) each
        equal = (sites[0] == sites[1]) & (sites[0] == sites[2]) & (sites[0] == sites[3])  # (H, W)
        if not bool(equal.all() if region is None else equal[region].all()):
            return False
    return True


def _box_mean(x: Tensor, weight: Tensor, size: int) -> Tensor:
    """(C, H, W) weighted means over ``size``² windows of ``weight`` (H, W) ≥ 0 (zero-weight pixels
    left out; a window without weight gives 0).

    Separable box sums of the zero-padded (C + 1, H, W) stack of x·weight and weight, by shifted
    in-place additions (on the CPU several times faster than a ``size``² ``avg_pool2d``)."""
    pad = size // 2
    c, h, w = x.shape
    padded = x.new_zeros((c + 1, h + 2 * pad, w + 2 * pad))
    torch.mul(x, weight, out=padded[:c, pad:pad + h, pad:pad + w])
    padded[c, pad:pad + h, pad:pad + w] = weight
    rows = padded[..., 0:w].clone()  # (C + 1, H + 2 pad, W): sums across
    for o in range(1, size):
        rows.add_(padded[..., o:o + w])
    del padded
    sums = rows[:, 0:h].clone()  # (C + 1, H, W): and down
    for o in range(1, size):
        sums.add_(rows[:, o:o + h])
    return sums[:c].div_(sums[c].clamp_min(1e-12))


def polarisation_dolp(capture: Capture, valid: Tensor, stokes: Tensor | None = None) -> tuple[float, int]:
    """How polarised the frames are: the :data:`POLARISATION_PERCENTILE` percentile of the DoLP of
    bilinear-demosaiced Stokes vectors averaged over :data:`POLARISATION_WINDOW`² windows of the
    usable, lit observations (module docstring).

    Args:
        capture: frames (K, 2H, 2W) counts, capture.yaml (bit depth, black level, mosaic).
        valid: (K, H, W) bool usable observations (preprocessing's ``valid``).
        stokes: (K, 3, H, W) those Stokes vectors when already at hand (preprocessing's with
            ``demosaic: bilinear`` at the block centres, in any per-pixel frames: the DoLP does not
            depend on the frame); None = demosaiced here from the frames.

    Returns:
        (DoLP percentile, number of observations it is taken over); (0.0, 0) without observations.
        One frame at a time: (2H, 2W) float64 intermediates only.
    """
    camera = capture.spec.camera
    valid = valid.cpu()
    values: list[np.ndarray] = []
    if not bool(valid.any()):
        return 0.0, 0
    # only the rows and columns with usable observations (plus the window and the demosaic's reach)
    rows, cols = torch.nonzero(valid.any(0), as_tuple=True)
    pad = POLARISATION_WINDOW // 2 + 1
    r0, r1 = max(int(rows.min()) - pad, 0), int(rows.max()) + pad + 1
    c0, c1 = max(int(cols.min()) - pad, 0), int(cols.max()) + pad + 1
    layout = capture.layout  # the crop starts on whole 2×2 blocks: the same layout
    for i in range(capture.frames.shape[0]):
        v = valid[i, r0:r1, c0:c1]  # (h, w)
        if not bool(v.any()):
            continue
        if stokes is None:
            raw = capture.frames[i, 2 * r0:2 * r1, 2 * c0:2 * c1]  # (2h, 2w): whole blocks, the layout unchanged
            # float32: the DoLP is compared with 0.01, far above float32 rounding
            mosaic = counts_to_float(raw, camera.bit_depth, camera.black_level, dtype=torch.float32)
            full = stokes_from_mosaic(mosaic, layout, "bilinear")  # (3, 2h, 2w); exact on linear fields
            frame = F.avg_pool2d(full.unsqueeze(0), 2)[0]  # (3, h, w) at the block centres
            del mosaic, full
        else:
            frame = stokes[i, :, r0:r1, c0:c1].to(device="cpu", dtype=torch.float32)  # (3, h, w)
        s0 = frame[0]
        v_np = v.numpy()  # (boolean indexing through numpy: several times faster than torch's on the CPU)
        lit = v & (s0 >= POLARISATION_LIT_FRACTION * float(np.percentile(s0.numpy()[v_np], 99.0)))
        mean = _box_mean(frame, lit.to(torch.float32), POLARISATION_WINDOW)  # (3, h, w)
        dolp = torch.hypot(mean[1], mean[2]).div_(mean[0].clamp_min(1e-12))  # (h, w)
        values.append(dolp.numpy()[lit.numpy()])  # (n,) the lit observations only
    if not values:
        return 0.0, 0
    pooled = np.concatenate(values)
    del values
    return float(np.percentile(pooled, POLARISATION_PERCENTILE, overwrite_input=True)), int(pooled.size)


def check_polarisation_signal(capture: Capture, inputs: RecoveryInputs, *, bilinear_centre: bool = False) -> float | None:
    """Refuse frames that carry no polarisation signal (a demosaiced or plain image read as a raw
    mosaic; module docstring).

    Args:
        capture: the capture preprocessed (frames (K, 2H, 2W)).
        inputs: its :class:`RecoveryInputs` (``valid`` (K, H, W), ``mask`` (H, W)).
        bilinear_centre: ``inputs.stokes`` are the bilinear estimates at the block centres (preprocess with
            ``demosaic: bilinear``, ``sample_at: centre``): reused instead of demosaicing the frames again.

    Returns:
        The measured :func:`polarisation_dolp`, or None when not judged: plain intensity frames
        (four equal sites), or fewer than :data:`POLARISATION_MIN_OBSERVATIONS` usable observations.

    Raises:
        CaptureError: the DoLP percentile below :data:`POLARISATION_DOLP_MIN`, naming it and the fix.
    """
    mask = inputs.mask.cpu().numpy()
    if is_plain_intensity(capture, mask if mask.any() else None):
        logger.debug("diagnose: plain intensity frames (four equal sites): no polarisation expected")
        return None
    dolp, n = polarisation_dolp(capture, inputs.valid & inputs.mask.unsqueeze(0),
                                inputs.stokes if bilinear_centre else None)
    if n < POLARISATION_MIN_OBSERVATIONS:
        logger.debug("diagnose: %d usable observations: too few to judge the polarisation signal", n)
        return None
    logger.debug("diagnose: polarisation signal: DoLP p%g %.4g over %d observations", POLARISATION_PERCENTILE, dolp, n)
    if dolp < POLARISATION_DOLP_MIN:
        raise CaptureError(
            f"capture: the frames carry no polarisation signal: the {POLARISATION_PERCENTILE:g}th percentile of the "
            f"degree of linear polarisation over its {n} usable object observations is {dolp:.4f} (Stokes vectors "
            f"averaged over {POLARISATION_WINDOW}x{POLARISATION_WINDOW} super-pixels), below {POLARISATION_DOLP_MIN} "
            "— a raw polarisation mosaic of an object shows more. The frames look like single demosaiced polariser "
            "images (or plain intensity images) saved as raw mosaics, whose neighbouring pixels would be taken for "
            "four polarisers: import demosaiced images with `polarshape import stack` (four images 0/45/90/135 per "
            "light), and plain intensity images with four equal sites per super-pixel (`polarshape import "
            "diligent`); if the frames really are raw mosaics of an unpolarised scene, set "
            "preprocess.polarisation_check: false"
        )
    return dolp
