"""Polarimetric calibration of a division-of-focal-plane camera from bench frames.

The bench procedure (README, "Polarimetric calibration"), each step optional except the polariser series:

1. **dark frames** (lens capped, the capture's exposure and gain): the per-pixel mean is the black
   level; pixels whose dark level lies far above the robust spread of all pixels are **hot**.
2. **flat frames** (a uniform *unpolarised* field — integrating sphere or opal diffuser, no
   polariser): the per-pixel response, normalised to mean 1 over good pixels, is the **gain**;
   pixels responding far below (or above) their neighbourhood are **dead** (or hot).
3. **polariser frames**: a linear polariser in front of the uniform source, at M ≥ 3 known angles ψ_j
   (6–12 recommended, spread over 180°). Each frame is first divided by its source brightness (the
   mean over blocks of ½ Σ of a block's four sites, which does not depend on ψ for ideal sites);
   then per pixel the linear least-squares fit ``I_j = a + b cos 2ψ_j + c sin 2ψ_j`` (ψ in our
   convention, spec §1) gives the analyser angle ``θ = ½ atan2(c, b)``, the diattenuation
   ``D = √(b² + c²) / a`` (clipped to (0, 1]) and, without flat frames, the gain ``∝ a``.
   A rotation mount's zero is not the sensor's x axis: unless ``absolute_angles``, the mean of
   θ − nominal over good pixels (the mount offset) is removed and recorded in ``info``.

The result is a :class:`polarshape.imaging.analyser.PolarimetricCalibration` (the forward formula is
:func:`polarshape.imaging.stokes.analyser_rows`); :mod:`polarshape.io.polarimetric` stores it.
:func:`estimate_polarimetric_calibration_from_files` reads image files and names them in its errors
(``polarshape calibrate polarisation``).
"""

from __future__ import annotations

import datetime as _dt
import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import ndimage

from polarshape.imaging.analyser import PolarimetricCalibration, extinction_from_diattenuation
from polarshape.imaging.mosaic import MakerAngles, MosaicLayout, our_angle_deg
from polarshape.imaging.pixels import check_bit_depth, max_count, saturation_count
from polarshape.io.images import read_image

logger = logging.getLogger(__name__)

__all__ = [
    "estimate_polarimetric_calibration",
    "estimate_polarimetric_calibration_from_files",
    "read_frames",
    "summarise_polarimetric_calibration",
]

#: A dark pixel this many robust σ (and at least _HOT_MIN_COUNTS) above the median dark level is hot.
_HOT_SIGMA = 10.0
_HOT_MIN_COUNTS = 4.0
#: A flat-field response below this fraction of its neighbourhood's is dead; above 1/this, hot.
_DEAD_FRACTION = 0.5
#: Frames of one series whose source levels differ by more than this factor are different exposures.
_POLARISER_LEVEL_RATIO = 2.0
_FLAT_LEVEL_RATIO = 1.1
#: A polariser series whose median diattenuation is below this does not modulate (no polariser).
_MIN_MEDIAN_DIATTENUATION = 0.2
#: After the mount offset, analysers further than this from their nominal angle (rms over pixels):
#: the angle convention or the layout is wrong.
_MAX_ANGLE_RMS_DEG = 10.0


def _names(prefix: str, n: int, names: Sequence[str] | None) -> list[str]:
    return [f"{prefix}[{i}]" for i in range(n)] if names is None else [str(x) for x in names]


def _check_series(frames: np.ndarray | None, what: str, bit_depth: int, shape: tuple[int, ...] | None,
                  names: Sequence[str] | None, flag: str) -> np.ndarray | None:
    """Validate one stack of raw frames (N, 2H, 2W) of integer counts; returns int64 counts."""
    if frames is None:
        return None
    arr = np.asarray(frames)
    if arr.ndim != 3 or arr.shape[0] == 0:
        raise ValueError(f"{what} must be a stack (N, 2H, 2W) of raw mosaics with N ≥ 1; got shape {arr.shape} ({flag})")
    labels = _names(what, arr.shape[0], names)
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{what}: frames must hold integer sensor counts (uint8/uint16 raw mosaics); got {arr.dtype}")
    h2, w2 = arr.shape[1:]
    if h2 % 2 or w2 % 2:
        raise ValueError(f"{labels[0]}: is {w2}×{h2} (W×H); a raw mosaic has even sides (whole 2×2 super-pixels)")
    if shape is not None and tuple(arr.shape[1:]) != tuple(shape):
        raise ValueError(
            f"{labels[0]} ({flag}): is {w2}×{h2} (W×H) but the polariser frames are {shape[1]}×{shape[0]}: all frames "
            "must come from the same camera, ROI and binning"
        )
    top = max_count(bit_depth)
    per_frame_max = arr.reshape(arr.shape[0], -1).max(1)
    bad = int(np.argmax(per_frame_max > top)) if bool((per_frame_max > top).any()) else None
    if bad is not None:
        raise ValueError(
            f"{labels[bad]} ({flag}): holds counts up to {int(per_frame_max[bad])}, above {top} = 2**{bit_depth} - 1 of "
            f"--bit-depth {bit_depth}: give the sensor's bit depth (16-bit files of 12-bit data high-bit aligned: "
            "shift them right by 4)"
        )
    return arr.astype(np.int64)


def _check_levels(levels: np.ndarray, ratio: float, labels: list[str], flag: str) -> None:
    """Raise when the frames' levels (N,) differ by more than ``ratio`` (different exposures mixed)."""
    lo, hi = int(np.argmin(levels)), int(np.argmax(levels))
    if levels[lo] <= 0 or levels[hi] / levels[lo] > ratio:
        raise ValueError(
            f"{flag}: {labels[hi]} is {levels[hi] / max(levels[lo], 1e-12):.2f}× as bright as {labels[lo]} "
            f"(levels {levels[hi]:.4g} and {levels[lo]:.4g} counts above black): these look like different exposures "
            "(or the source changed); take every frame of a series at one exposure and gain, with a stable source"
        )


def _robust_sigma(x: np.ndarray) -> float:
    med = np.median(x)
    return float(1.4826 * np.median(np.abs(x - med)))


def _dark_stage(dark: np.ndarray | None, black_level: float, shape: tuple[int, int], bit_depth: int,
                labels: list[str]) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Per-pixel black level (2H, 2W) counts, hot pixels (2H, 2W) bool, and info."""
    if dark is None:
        return np.full(shape, float(black_level)), np.zeros(shape, bool), {"black_level": "constant", "black": black_level}
    black = dark.mean(0)  # (2H, 2W)
    med = float(np.median(black))
    if med > 0.25 * max_count(bit_depth):
        raise ValueError(
            f"--dark: the dark frames' median level is {med:.0f} counts, {100 * med / max_count(bit_depth):.0f} % of full "
            "scale: these are not dark frames; cap the lens (or cover the sensor) and take them at the capture's exposure"
        )
    sigma = _robust_sigma(black)
    hot = black > med + max(_HOT_SIGMA * sigma, _HOT_MIN_COUNTS)
    return black, hot, {"black_level": "dark frames", "dark_frames": len(labels), "black_median": med,
                        "black_spread": sigma, "hot_threshold": med + max(_HOT_SIGMA * sigma, _HOT_MIN_COUNTS)}


def _flat_stage(flat: np.ndarray, black: np.ndarray, labels: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat response (2H, 2W) counts above black, dead and hot (stuck-high) pixels (2H, 2W) bool."""
    levels = (flat - black).reshape(flat.shape[0], -1).mean(1)
    _check_levels(levels, _FLAT_LEVEL_RATIO, labels, "--flat")
    response = flat.mean(0) - black  # (2H, 2W)
    local = ndimage.median_filter(response, size=5, mode="reflect")
    floor = max(float(np.median(response)) * 1e-3, 1e-9)
    dead = response < _DEAD_FRACTION * np.maximum(local, floor)
    stuck = response > np.maximum(local, floor) / _DEAD_FRACTION
    if dead.mean() > 0.5:
        raise ValueError("--flat: most pixels respond at less than half their neighbourhood's level: is the field lit and "
                         "uniform? Use an integrating sphere or an evenly lit diffuser filling the view")
    return response, dead, stuck


def _source_levels(frames: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """(M,) each frame's mean over usable blocks of ½ Σ of the block's four sites (counts)."""
    m, h2, w2 = frames.shape
    blocks = 0.5 * frames.reshape(m, h2 // 2, 2, w2 // 2, 2).sum((2, 4))  # (M, H, W)
    ok = usable.reshape(m, h2 // 2, 2, w2 // 2, 2).all((2, 4))  # (M, H, W)
    common = ok.all(0)
    if common.sum() >= 16:  # the same blocks in every frame (vignetting weighs alike)
        ok = np.broadcast_to(common, ok.shape)
    return np.array([blocks[j][ok[j]].mean() if ok[j].any() else 0.0 for j in range(m)])


def _fit_cosines(intensity: np.ndarray, weight: np.ndarray, psi_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel weighted least squares ``I_j = a + b cos 2ψ_j + c sin 2ψ_j``.

    Args:
        intensity: (M, P) normalised intensities, weight (M, P) in {0, 1}, psi_rad (M,).

    Returns:
        coefficients (P, 3), rms residual (P,), and which pixels were determined (P,) bool.
    """
    x = np.stack([np.ones_like(psi_rad), np.cos(2 * psi_rad), np.sin(2 * psi_rad)], axis=1)  # (M, 3)
    xt = torch.from_numpy(x)
    w = torch.from_numpy(weight.astype(np.float64))  # (M, P)
    y = torch.from_numpy(intensity)
    gram = torch.einsum("mp,mi,mj->pij", w, xt, xt)  # (P, 3, 3)
    rhs = torch.einsum("mp,mi,mp->pi", w, xt, y)  # (P, 3)
    det = torch.linalg.det(gram)
    ok = (w.sum(0) >= 3) & (det > 1e-6 * gram.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(1e-300) ** 3)
    eye = torch.eye(3, dtype=gram.dtype)
    coef = torch.linalg.solve(torch.where(ok[:, None, None], gram, eye), rhs.unsqueeze(-1)).squeeze(-1)
    coef = torch.where(ok[:, None], coef, torch.zeros_like(coef))
    resid = (y - (xt @ coef.T)) * w  # (M, P)
    dof = (w.sum(0) - 3).clamp_min(1)
    rms = torch.sqrt((resid**2).sum(0) / dof)
    return coef.numpy(), rms.numpy(), ok.numpy()


def _wrap_half_turn(x: np.ndarray) -> np.ndarray:
    """Angles (radians) wrapped to [−π/2, π/2)."""
    return np.remainder(x + math.pi / 2, math.pi) - math.pi / 2


def estimate_polarimetric_calibration(
    *,
    polariser: np.ndarray,
    angles_deg: Sequence[float],
    angle_convention: MakerAngles = "counterclockwise_on_screen",
    layout: MosaicLayout,
    bit_depth: int,
    flat: np.ndarray | None = None,
    dark: np.ndarray | None = None,
    black_level: float = 0.0,
    absolute_angles: bool = False,
) -> PolarimetricCalibration:
    """Estimate the sensor's per-pixel analysers, gains, black level and defects (module docstring).

    Args:
        polariser: (M, 2H, 2W) integer counts, a linear polariser in front of a uniform source at the
            M ≥ 3 angles ``angles_deg`` (average several frames per angle for less noise).
        angles_deg: (M,) the polariser's angle for each frame, degrees, in ``angle_convention``
            (the rotation mount's scale; its zero may be anywhere unless ``absolute_angles``).
        angle_convention: how the angles are measured (:data:`polarshape.imaging.mosaic.MAKER_ANGLES`):
            ``"counterclockwise_on_screen"`` (default, the makers': increasing from image x toward
            image *up* as seen on screen), ``"clockwise_on_screen"`` (ours: toward image y, down),
            ``"polanalyser"`` (the same as the makers').
        layout: the sensor's mosaic layout (our convention), for the nominal site angles.
        bit_depth: significant bits of the counts.
        flat: (N, 2H, 2W) counts of a uniform unpolarised field (no polariser), or None.
        dark: (D, 2H, 2W) counts with the lens capped, or None (then ``black_level`` everywhere).
        black_level: the constant black level (counts) used without dark frames.
        absolute_angles: the polariser angles are absolute (from the sensor's x axis): keep the
            global offset instead of removing it.

    Returns:
        :class:`PolarimetricCalibration` with ``info`` holding the summary figures (angle error rms/max
        in degrees, extinction ratio median and 5th percentile, gain spread, hot/dead counts, the
        removed mount offset, residuals).

    Raises:
        ValueError: fewer than 3 polariser frames or angles, an angle list of another length, frames of
            different sizes, counts above the bit depth, frames of different exposures in one series,
            dark frames that are not dark, a polariser series that does not modulate, analysers far
            from the layout's angles (a wrong ``angle_convention`` or ``layout``).
    """
    return _estimate(polariser=polariser, angles_deg=angles_deg, angle_convention=angle_convention, layout=layout,
                     bit_depth=bit_depth, flat=flat, dark=dark, black_level=black_level,
                     absolute_angles=absolute_angles)


def _estimate(*, polariser: np.ndarray, angles_deg: Sequence[float], angle_convention: MakerAngles,
              layout: MosaicLayout, bit_depth: int, flat: np.ndarray | None, dark: np.ndarray | None,
              black_level: float, absolute_angles: bool, names: dict[str, Sequence[str]] | None = None) -> PolarimetricCalibration:
    bit_depth = check_bit_depth(bit_depth)
    names = names or {}
    if not isinstance(layout, MosaicLayout):
        raise TypeError(f"layout must be a MosaicLayout; got {type(layout).__name__}")
    pol = _check_series(polariser, "polariser", bit_depth, None, names.get("polariser"), "--polariser")
    assert pol is not None
    angles = [float(a) for a in angles_deg]
    if not all(math.isfinite(a) for a in angles):
        raise ValueError(f"--angles must be finite numbers (degrees); got {angles}")
    if len(angles) != pol.shape[0]:
        raise ValueError(
            f"--angles: {len(angles)} angles for {pol.shape[0]} polariser frames; give one angle per --polariser frame, "
            "in the same order"
        )
    if pol.shape[0] < 3:
        raise ValueError(
            f"--polariser: {pol.shape[0]} frames; the analyser fit needs the polariser at ≥ 3 angles (6–12 spread over "
            "180° recommended, e.g. every 15°)"
        )
    shape = (int(pol.shape[1]), int(pol.shape[2]))
    if not 0 <= black_level < max_count(bit_depth):
        raise ValueError(f"--black-level {black_level} must lie in [0, {max_count(bit_depth)}) for --bit-depth {bit_depth}")
    drk = _check_series(dark, "dark", bit_depth, shape, names.get("dark"), "--dark")
    flt = _check_series(flat, "flat", bit_depth, shape, names.get("flat"), "--flat")
    pol_labels = _names("polariser", pol.shape[0], names.get("polariser"))

    # our angles, unwrapped (2ψ is what matters); the sign of the convention mirrors them
    psi = np.radians([our_angle_deg(a, angle_convention) for a in angles])  # (M,)
    two = np.exp(2j * psi)
    if np.abs(two - two[0]).max() < math.radians(5.0):
        raise ValueError(f"--angles {angles}: all (nearly) the same polariser angle; spread them over 180°")

    black, hot, info = _dark_stage(drk, black_level, shape, bit_depth, _names("dark", 0 if drk is None else drk.shape[0], names.get("dark")))
    defects = hot.copy()
    n_dead = 0
    n_hot = int(hot.sum())
    response = None
    if flt is not None:
        response, dead, stuck = _flat_stage(flt, black, _names("flat", flt.shape[0], names.get("flat")))
        n_dead, n_hot = int((dead & ~defects).sum()), n_hot + int((stuck & ~defects).sum())
        defects |= dead | stuck

    # polariser series: drop clipped samples, normalise each frame by its source brightness
    clipped = pol >= saturation_count(bit_depth)  # (M, 2H, 2W)
    signal = pol - black  # (M, 2H, 2W) counts above black
    usable = ~clipped & ~defects
    levels = _source_levels(signal, usable)
    _check_levels(levels, _POLARISER_LEVEL_RATIO, pol_labels, "--polariser")
    norm = signal / levels[:, None, None]  # (M, 2H, 2W) ≈ ½ g (1 + D cos 2(θ − ψ))
    m = pol.shape[0]
    coef, rms, determined = _fit_cosines(norm.reshape(m, -1), usable.reshape(m, -1), psi)
    a, b, c = (coef[:, k].reshape(shape) for k in range(3))
    determined = determined.reshape(shape) & (a > 0)
    n_undetermined = int((~determined & ~defects).sum())
    defects |= ~determined

    good = ~defects
    if not good.any():
        raise ValueError("--polariser: no pixel could be calibrated (all clipped or defective); lower the exposure")
    safe_a = np.where(determined, a, 1.0)
    d_raw = np.hypot(b, c) / safe_a
    median_d = float(np.median(d_raw[good]))
    if median_d < _MIN_MEDIAN_DIATTENUATION:
        raise ValueError(
            f"--polariser: the frames barely change with the polariser angle (median diattenuation {median_d:.3f}): is "
            "there a linear polariser in front of the source, and was it rotated between frames?"
        )
    diattenuation = np.clip(d_raw, 1e-6, 1.0)
    theta = 0.5 * np.arctan2(c, b)  # (2H, 2W) in (−π/2, π/2]
    nominal = np.radians(np.array(layout.angles_deg, dtype=np.float64))  # (2, 2)
    nominal = np.tile(nominal, (shape[0] // 2, shape[1] // 2))  # (2H, 2W)
    delta = _wrap_half_turn(theta - nominal)
    # mount offset: circular mean of 2Δ over good pixels (robust to the wrap)
    offset = 0.5 * math.atan2(float(np.sin(2 * delta[good]).mean()), float(np.cos(2 * delta[good]).mean()))
    if not absolute_angles:
        delta = _wrap_half_turn(delta - offset)
    angle_rad = nominal + delta
    err_deg = np.degrees(delta[good])
    err_rms = float(np.sqrt(np.mean(err_deg**2)))
    if err_rms > _MAX_ANGLE_RMS_DEG:
        raise ValueError(
            f"--angles: the analysers come out {err_rms:.1f}° rms from the layout's nominal angles: the polariser angles "
            f"run the other way (try --angle-convention {'clockwise_on_screen' if angle_convention != 'clockwise_on_screen' else 'counterclockwise_on_screen'}), "
            "or --layout is not the sensor's" + ("" if not absolute_angles else ", or the angles are not absolute")
        )

    gain_raw = response if response is not None else 2.0 * safe_a
    gain = gain_raw / float(np.mean(gain_raw[good]))
    gain = np.where(good & (gain > 0), gain, 1.0)
    diattenuation = np.where(good, diattenuation, 1.0)
    # D clipped at 1 (noise) is an infinite ER: cap the statistics at 10⁶:1 (finite in params.json)
    er = np.minimum(extinction_from_diattenuation(torch.from_numpy(diattenuation[good])).numpy(), 1e6)
    info.update({
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "polariser_frames": m,
        "angles_deg": angles,
        "angle_convention": angle_convention,
        "layout_deg": [list(r) for r in layout.angles_deg],
        "absolute_angles": bool(absolute_angles),
        "mount_offset_deg": math.degrees(offset),
        "offset_removed": not absolute_angles,
        "flat_frames": 0 if flt is None else int(flt.shape[0]),
        "gain_from": "flat frames" if flt is not None else "polariser fit",
        "source_levels": [float(v) for v in levels],
        "angle_error_rms_deg": err_rms,
        "angle_error_max_deg": float(np.abs(err_deg).max()),
        "extinction_median": float(np.median(er)),
        "extinction_p5": float(np.percentile(er, 5)),
        "diattenuation_median": float(np.median(diattenuation[good])),
        "gain_spread": float(np.std(gain[good])),
        "fit_residual_rms": float(np.median(rms.reshape(shape)[good])),
        "hot": n_hot,
        "dead": n_dead,
        "undetermined": n_undetermined,
        "defects": int(defects.sum()),
    })
    cal = PolarimetricCalibration(
        angle_rad=torch.from_numpy(angle_rad), diattenuation=torch.from_numpy(diattenuation),
        gain=torch.from_numpy(gain), black_level=torch.from_numpy(black.astype(np.float64)),
        defects=torch.from_numpy(defects), bit_depth=bit_depth, info=info,
    )
    logger.info("polarimetric calibration: %s", summarise_polarimetric_calibration(cal))
    return cal


def summarise_polarimetric_calibration(calibration: PolarimetricCalibration) -> str:
    """One line of the figures in ``calibration.info`` (what ``calibrate polarisation`` prints)."""
    i = calibration.info
    if "angle_error_rms_deg" not in i:
        return f"{calibration.shape[1]}×{calibration.shape[0]} calibration (no summary recorded)"
    p5 = i["extinction_p5"]
    return (
        f"{calibration.shape[1]}×{calibration.shape[0]} pixels: analyser angle error {i['angle_error_rms_deg']:.2f}° rms, "
        f"{i['angle_error_max_deg']:.2f}° max (mount offset {i['mount_offset_deg']:+.2f}°"
        f"{' removed' if i.get('offset_removed') else ' kept'}); extinction ratio median {i['extinction_median']:.0f}:1, "
        f"5th percentile {p5:.0f}:1; gain spread {100 * i['gain_spread']:.2f} % (from {i['gain_from']}); "
        f"{i['hot']} hot, {i['dead']} dead, {i.get('undetermined', 0)} undetermined pixels"
    )


def read_frames(paths: Sequence[str | os.PathLike[str]], flag: str) -> np.ndarray:
    """(N, 2H, 2W) raw mosaics read from ``paths`` (8/16-bit PNG/TIFF); errors name the file and ``flag``."""
    images = [read_image(p) for p in paths]
    first = images[0].shape
    for p, im in zip(paths, images):
        if im.shape != first:
            raise ValueError(
                f"{p} ({flag}): is {im.shape[1]}×{im.shape[0]} (W×H) but {paths[0]} is {first[1]}×{first[0]}: all "
                "frames must come from the same camera, ROI and binning"
            )
    return np.stack([im.astype(np.uint16, copy=False) for im in images])


def estimate_polarimetric_calibration_from_files(
    *,
    polariser: Sequence[str | os.PathLike[str]],
    angles_deg: Sequence[float],
    angle_convention: MakerAngles = "counterclockwise_on_screen",
    layout: MosaicLayout,
    bit_depth: int,
    flat: Sequence[str | os.PathLike[str]] = (),
    dark: Sequence[str | os.PathLike[str]] = (),
    black_level: float = 0.0,
    absolute_angles: bool = False,
) -> PolarimetricCalibration:
    """:func:`estimate_polarimetric_calibration` of image files; its errors name the files.

    Raises:
        ImageError: a missing or unreadable image; ValueError: as the estimator (file names given).
    """
    if len(polariser) < 3:
        raise ValueError(f"--polariser: {len(polariser)} frames given; the fit needs the polariser at ≥ 3 angles "
                         "(6–12 spread over 180° recommended)")
    if len(angles_deg) != len(polariser):
        raise ValueError(f"--angles: {len(angles_deg)} angles for {len(polariser)} --polariser frames; give one angle per "
                         "frame, in the same order")
    pol = read_frames(polariser, "--polariser")
    flt = read_frames(flat, "--flat") if flat else None
    drk = read_frames(dark, "--dark") if dark else None
    for arr, paths, flag in ((flt, flat, "--flat"), (drk, dark, "--dark")):
        if arr is not None and arr.shape[1:] != pol.shape[1:]:
            raise ValueError(
                f"{paths[0]} ({flag}): is {arr.shape[2]}×{arr.shape[1]} (W×H) but the polariser frames are "
                f"{pol.shape[2]}×{pol.shape[1]}: all frames must come from the same camera, ROI and binning"
            )
    cal = _estimate(polariser=pol, angles_deg=angles_deg, angle_convention=angle_convention, layout=layout,
                    bit_depth=bit_depth, flat=flt, dark=drk, black_level=black_level, absolute_angles=absolute_angles,
                    names={"polariser": [str(p) for p in polariser], "flat": [str(p) for p in flat],
                           "dark": [str(p) for p in dark]})
    cal.info["files"] = {"polariser": [Path(p).name for p in polariser], "flat": [Path(p).name for p in flat],
                         "dark": [Path(p).name for p in dark]}
    return cal
