"""The sensor's real analysers, per pixel: polariser angle, diattenuation, gain, black level, defects.

A division-of-focal-plane sensor's micro-polarisers are not ideal: each pixel's transmission axis is a
little off its nominal 0/45/90/135°, it leaks light polarised across it (extinction ratio ER =
t_max / t_min, diattenuation D = (ER − 1)/(ER + 1)), and pixels differ in response (PRNU) and dark
level; a few are hot or dead. One pixel records (counts, before quantisation)

    c = black + (full scale − black_nominal) · row · s,   row = ½ g [1, D cos 2θ, D sin 2θ]

(:func:`polarshape.imaging.stokes.analyser_rows`, the one place of that formula) for the linear Stokes
vector ``s`` in fractions of full scale, spec §1 convention. :class:`PolarimetricCalibration` holds
those per-pixel quantities at raw-mosaic resolution; the ideal sensor is θ = the layout's angles,
D = 1, g = 1, black = the capture's ``camera.black_level``, no defects. A calibration is estimated by
``polarshape calibrate polarisation`` (bench frames), stored by :mod:`polarshape.io.polarimetric`,
referenced from capture.yaml as ``camera.polarimetric_calibration`` and applied when the Stokes
vectors are computed; the simulator draws one for its imperfect sensor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import torch
from torch import Tensor

from polarshape.checks import check_dtype_floating, format_shape
from polarshape.errors import ShapeError
from polarshape.imaging.demosaic import intensities_from_mosaic
from polarshape.imaging.mosaic import MosaicLayout, check_layout, check_mosaic_shape
from polarshape.imaging.stokes import analyser_rows

__all__ = [
    "CALIBRATED_METHODS",
    "PolarimetricCalibration",
    "analysed_intensity",
    "calibrated_pinv",
    "calibrated_stokes",
    "ideal_equivalent_sites",
    "diattenuation_from_extinction",
    "extinction_from_diattenuation",
]


def diattenuation_from_extinction(extinction_ratio: Tensor | float) -> Tensor:
    """D = (ER − 1) / (ER + 1) of an extinction ratio ER = t_max / t_min ≥ 1 (ER = inf → D = 1)."""
    er = torch.as_tensor(extinction_ratio, dtype=torch.float64)
    return torch.where(torch.isinf(er), torch.ones_like(er), (er - 1.0) / (er + 1.0).clamp_min(1.0))


def extinction_from_diattenuation(diattenuation: Tensor | float) -> Tensor:
    """ER = (1 + D) / (1 − D) of a diattenuation D in (0, 1] (D = 1 → inf)."""
    d = torch.as_tensor(diattenuation, dtype=torch.float64)
    return torch.where(d >= 1.0, torch.full_like(d, math.inf), (1.0 + d) / (1.0 - d).clamp_min(1e-300))


def analysed_intensity(stokes: Tensor, angle_rad: Tensor, diattenuation: Tensor | float = 1.0,
                       gain: Tensor | float = 1.0) -> Tensor:
    """What each raw pixel behind its own real analyser sees: ``row · s`` (module docstring).

    Args:
        stokes: (*, 3, H, W) Stokes vectors at raw-mosaic resolution, sensor-plane angles.
        angle_rad: (H, W) transmission-axis angle of every pixel, radians (our convention).
        diattenuation: (H, W) or scalar D in (0, 1].
        gain: (H, W) or scalar relative gain.

    Returns:
        (*, H, W) radiance behind the analysers (dtype and device of ``stokes``).
    """
    stokes = check_dtype_floating(stokes, "stokes")
    if stokes.ndim < 3 or stokes.shape[-3] != 3 or tuple(angle_rad.shape) != tuple(stokes.shape[-2:]):
        raise ShapeError(
            f"stokes must be (*, 3, H, W) and angle_rad (H, W) of the same H, W; got {format_shape(stokes.shape)} "
            f"and {format_shape(angle_rad.shape)}"
        )
    rows = analyser_rows(angle_rad.to(stokes), _as(diattenuation, stokes), _as(gain, stokes))  # (H, W, 3)
    return torch.einsum("hwc,...chw->...hw", rows, stokes)


def _as(x: Tensor | float, like: Tensor) -> Tensor:
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)


@dataclass(frozen=True)
class PolarimetricCalibration:
    """Per-pixel analyser and dark-signal description of one sensor (module docstring).

    Attributes:
        angle_rad: (2H, 2W) float64 transmission-axis angle of every raw pixel, radians, our
            convention (image x toward image y, down).
        diattenuation: (2H, 2W) float64 D in (0, 1] (1 = perfect polariser).
        gain: (2H, 2W) float64 relative response g > 0 (1 = nominal; PRNU and t_max + t_min).
        black_level: (2H, 2W) float64 dark level in counts of ``bit_depth``.
        defects: (2H, 2W) bool hot or dead pixels (their counts carry no signal).
        bit_depth: significant bits of the counts ``black_level`` is given in.
        info: how it was made (frames, residuals, dates): JSON-serialisable, kept with the file.
    """

    angle_rad: Tensor
    diattenuation: Tensor
    gain: Tensor
    black_level: Tensor
    defects: Tensor
    bit_depth: int
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        shape = tuple(self.angle_rad.shape)
        if len(shape) != 2 or shape[0] % 2 or shape[1] % 2 or 0 in shape:
            raise ShapeError(f"angle_rad must be (2H, 2W) with even, non-zero sides; got {format_shape(shape)}")
        for name in ("diattenuation", "gain", "black_level", "defects"):
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ShapeError(f"{name} must have the shape of angle_rad {format_shape(shape)}; got {format_shape(got)}")
        for name in ("angle_rad", "diattenuation", "gain", "black_level"):
            if not bool(torch.isfinite(getattr(self, name)).all()):
                raise ValueError(f"PolarimetricCalibration.{name} holds NaN or Inf")
        if self.defects.dtype != torch.bool:
            raise TypeError(f"defects must be a bool tensor; got {self.defects.dtype}")
        good = ~self.defects
        d, g = self.diattenuation[good], self.gain[good]
        if d.numel() and not (bool((d > 0).all()) and bool((d <= 1 + 1e-9).all())):
            raise ValueError("PolarimetricCalibration.diattenuation must lie in (0, 1] on every non-defective pixel")
        if g.numel() and not bool((g > 0).all()):
            raise ValueError("PolarimetricCalibration.gain must be > 0 on every non-defective pixel")

    @property
    def shape(self) -> tuple[int, int]:
        """(2H, 2W) raw-mosaic size."""
        return (int(self.angle_rad.shape[0]), int(self.angle_rad.shape[1]))

    @classmethod
    def ideal(cls, layout: MosaicLayout, height: int, width: int, *, bit_depth: int,
              black_level: float = 0.0) -> PolarimetricCalibration:
        """The ideal sensor of ``layout`` over a (height, width) raw mosaic (even sides)."""
        if height % 2 or width % 2 or height <= 0 or width <= 0:
            raise ValueError(f"mosaic height and width must be even and positive; got {height}x{width}")
        sites = layout.angles_rad(dtype=torch.float64).reshape(2, 2)  # (2, 2)
        angle = sites.repeat(height // 2, width // 2)  # (2H, 2W)
        ones = torch.ones_like(angle)
        return cls(angle_rad=angle, diattenuation=ones, gain=ones.clone(), black_level=ones * float(black_level),
                   defects=torch.zeros_like(angle, dtype=torch.bool), bit_depth=int(bit_depth))

    def rows(self, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> Tensor:
        """(2H, 2W, 3) analyser rows ``½ g [1, D cos 2θ, D sin 2θ]`` of every pixel (defects: zero rows)."""
        rows = analyser_rows(self.angle_rad, self.diattenuation, self.gain)
        rows = torch.where(self.defects.unsqueeze(-1), torch.zeros_like(rows), rows)
        return rows.to(dtype=dtype, device=device)

    def extinction_ratio(self) -> Tensor:
        """(2H, 2W) ER = (1 + D) / (1 − D) (inf for D = 1)."""
        return extinction_from_diattenuation(self.diattenuation)


#: How :func:`calibrated_stokes` combines the sites: one estimate per 2×2 block, or one per raw pixel
#: from every angle class interpolated to it (with its rows).
CALIBRATED_METHODS: tuple[str, ...] = ("superpixel", "bilinear")
CalibratedMethod = Literal["superpixel", "bilinear"]

#: A calibration's per-site angles may differ from the layout's nominal ones by at most this much
#: (median per site class) before it is taken for another layout or a shifted ROI.
_LAYOUT_TOLERANCE_DEG = 20.0


def _check_layout_match(calibration: PolarimetricCalibration, layout: MosaicLayout) -> None:
    """Raise ValueError unless the calibration's angles sit near ``layout``'s nominal site angles."""
    nominal = layout.angles_rad(dtype=torch.float64).reshape(2, 2)
    for i in range(2):
        for j in range(2):
            site = calibration.angle_rad[i::2, j::2][~calibration.defects[i::2, j::2]]
            if site.numel() == 0:
                continue
            diff = torch.remainder(site - nominal[i, j] + math.pi / 2, math.pi) - math.pi / 2
            off = math.degrees(abs(float(diff.median())))
            if off > _LAYOUT_TOLERANCE_DEG:
                raise ValueError(
                    f"the polarimetric calibration's site ({i}, {j}) analysers are {off:.1f}° from the layout's "
                    f"{layout.angles_deg[i][j]:.0f}°: it was made for another mosaic layout or region of interest "
                    "(an odd ROI offset shifts the pattern); calibrate with the capture's camera.mosaic and ROI"
                )


def _pinv_of_rows(rows: Tensor) -> tuple[Tensor, Tensor]:
    """Least-squares inverses (*, 3, 4) of analysis matrices (*, 4, 3) and their validity (*) (rank 3).

    A zero row (a defect, a class with no usable neighbour) drops out of the fit; three independent
    rows determine ``s`` exactly. Rank-deficient matrices get a zero inverse (no NaN)."""
    gram = rows.transpose(-1, -2) @ rows  # (*, 3, 3)
    # rank 3 ⇔ det well away from 0 relative to the scale of the rows (⅛ for ideal rows)
    scale = gram.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(1e-300)  # (*)
    valid = torch.linalg.det(gram) > 1e-6 * scale**3
    eye = torch.eye(3, dtype=rows.dtype, device=rows.device)
    safe = torch.where(valid[..., None, None], gram, eye)
    pinv = torch.linalg.solve(safe, rows.transpose(-1, -2))  # (*, 3, 4)
    return torch.where(valid[..., None, None], pinv, torch.zeros_like(pinv)), valid


def calibrated_pinv(calibration: PolarimetricCalibration, layout: MosaicLayout, *,
                    method: CalibratedMethod = "superpixel", device: torch.device | str | None = None) -> tuple[Tensor, Tensor]:
    """The per-block or per-pixel pseudo-inverses that :func:`calibrated_stokes` applies.

    ``"superpixel"``: each 2×2 block's four rows (sites (0, 0), (0, 1), (1, 0), (1, 1)) form a 4×3
    analysis matrix A; ``s = (AᵀA)⁻¹Aᵀ I``. A defective site's row is zero, so the three others
    determine ``s``; a block with ≥ 2 defects is invalid. ``"bilinear"``: every angle class is
    interpolated bilinearly to every raw pixel (:func:`polarshape.imaging.demosaic.intensities_from_mosaic`)
    from its non-defective samples, and so are their rows (``I = row · s`` with ``s`` locally
    constant gives ``Σ w I = (Σ w row) · s``), so each pixel has its own 4×3 matrix.

    Args:
        calibration: the sensor's calibration, (2H, 2W).
        layout: mosaic layout of the frames (our convention); the calibration's angles must match it.
        method: ``"superpixel"`` or ``"bilinear"``.
        device: of the result (float64).

    Returns:
        P (H, W, 3, 4) and valid (H, W) bool for ``"superpixel"``; P (2H, 2W, 3, 4) (the columns in
        channel order 0°, 45°, 90°, 135°) and valid (2H, 2W) for ``"bilinear"``.
    """
    layout = check_layout(layout)
    if method not in CALIBRATED_METHODS:
        raise ValueError(f"method must be one of {CALIBRATED_METHODS}; got {method!r}")
    _check_layout_match(calibration, layout)
    rows = calibration.rows(device=device)  # (2H, 2W, 3), zero rows at defects
    if method == "superpixel":
        h2, w2 = calibration.shape
        blocks = rows.reshape(h2 // 2, 2, w2 // 2, 2, 3).permute(0, 2, 1, 3, 4).reshape(h2 // 2, w2 // 2, 4, 3)
        pinv, valid = _pinv_of_rows(blocks)
        n_defects = calibration.defects.to(device).reshape(h2 // 2, 2, w2 // 2, 2).sum((1, 3))  # (H, W)
        return pinv, valid & (n_defects < 2)
    # the rows' components interpolated like the intensities: (3, 4, 2H, 2W) -> (2H, 2W, 4, 3)
    interp = intensities_from_mosaic(rows.permute(2, 0, 1).contiguous(), layout, "bilinear")
    return _pinv_of_rows(interp.permute(2, 3, 1, 0))


def calibrated_stokes(mosaic: Tensor, calibration: PolarimetricCalibration, layout: MosaicLayout, *,
                      method: CalibratedMethod = "superpixel",
                      pinv: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Linear Stokes vectors of raw mosaics seen through the sensor's calibrated analysers.

    The mosaic must already have the per-pixel black level subtracted and be scaled to fractions of
    full scale (``(counts − calibration.black_level) / (max_count − nominal black)``); the gains are
    in the rows, so the mosaic is NOT divided by them.

    Args:
        mosaic: (*, 2H, 2W) floating point, the calibration's size.
        calibration: :class:`PolarimetricCalibration` of the sensor (ROI as the frames').
        layout: mosaic layout of the frames (our convention).
        method: ``"superpixel"`` (one vector per 2×2 block) or ``"bilinear"`` (one per raw pixel;
            see :func:`calibrated_pinv`).
        pinv: the result of :func:`calibrated_pinv` for these arguments (reuse over many frames).

    Returns:
        stokes (*, 3, H, W) (``"bilinear"``: (*, 3, 2H, 2W)), dtype of ``mosaic``, spec §1 convention;
        valid (H, W) (or (2H, 2W)) bool: False where too few good sites determine ``s`` (its vector
        is 0 there).

    Example:
        >>> cal = PolarimetricCalibration.ideal(MosaicLayout.imx250mzr(), 4, 4, bit_depth=12)
        >>> s, ok = calibrated_stokes(torch.full((4, 4), 0.5, dtype=torch.float64), cal, MosaicLayout.imx250mzr())
        >>> [round(v, 9) for v in s[:, 0, 0].tolist()], bool(ok.all())
        ([1.0, 0.0, 0.0], True)
    """
    mosaic = check_dtype_floating(check_mosaic_shape(mosaic), "mosaic")
    if tuple(mosaic.shape[-2:]) != calibration.shape:
        raise ShapeError(
            f"mosaic must be (*, 2H, 2W) of the calibration's size {format_shape(calibration.shape)}; got "
            f"{format_shape(mosaic.shape)} (calibrate the same sensor region: ROI, binning)"
        )
    p, valid = calibrated_pinv(calibration, layout, method=method, device=mosaic.device) if pinv is None else pinv
    m = mosaic.to(torch.float64)
    if method == "superpixel":
        *lead, h2, w2 = m.shape
        sites = m.reshape(*lead, h2 // 2, 2, w2 // 2, 2).movedim(-3, -2).reshape(*lead, h2 // 2, w2 // 2, 4)
    else:
        good = (~calibration.defects).to(m)  # defective samples take no part in the interpolation
        sites = intensities_from_mosaic(m * good, layout, "bilinear").movedim(-3, -1)  # (*, 2H, 2W, 4)
    s = torch.einsum("hwck,...hwk->...chw", p.to(m.device), sites)
    return s.to(mosaic.dtype), valid.to(mosaic.device)


def ideal_equivalent_sites(mosaic: Tensor, calibration: PolarimetricCalibration, layout: MosaicLayout, *,
                           pinv: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """The four site intensities ideal analysers would have recorded, for the consistency checks.

    Each block's calibrated Stokes vector ``s`` (``"superpixel"``) seen through ideal rows, plus the
    block's own least-squares residual ``r = I − A s`` (zero at defects): ``A_ideal s + r``. The
    four-site redundancy d = (I0 + I90) − (I45 + I135) of these is the calibrated fit's misfit — noise
    and scene structure within the block — and no longer the sensor's PRNU or analyser errors; for
    the ideal calibration they are the raw sites.

    Args:
        mosaic: (*, 2H, 2W) as for :func:`calibrated_stokes` (black subtracted, fractions of full scale).
        calibration, layout: as for :func:`calibrated_stokes`.
        pinv: :func:`calibrated_pinv` with ``method="superpixel"`` (reuse over frames).

    Returns:
        (*, 4, H, W) intensities at 0°, 45°, 90°, 135° (channel order of
        :func:`polarshape.imaging.mosaic.split_mosaic`), float64.
    """
    s, _ = calibrated_stokes(mosaic, calibration, layout, method="superpixel", pinv=pinv)  # (*, 3, H, W)
    s = s.to(torch.float64)
    m = mosaic.to(torch.float64)
    h2, w2 = calibration.shape
    *lead, _, _ = m.shape
    sites = m.reshape(*lead, h2 // 2, 2, w2 // 2, 2).movedim(-3, -2).reshape(*lead, h2 // 2, w2 // 2, 4)
    rows = calibration.rows(device=m.device)  # (2H, 2W, 3)
    rows = rows.reshape(h2 // 2, 2, w2 // 2, 2, 3).permute(0, 2, 1, 3, 4).reshape(h2 // 2, w2 // 2, 4, 3)
    defects = calibration.defects.to(m.device).reshape(h2 // 2, 2, w2 // 2, 2).permute(0, 2, 1, 3).reshape(h2 // 2, w2 // 2, 4)
    fitted = torch.einsum("hwkc,...chw->...hwk", rows, s)  # (*, H, W, 4)
    residual = torch.where(defects, torch.zeros_like(sites), sites - fitted)
    ideal = analyser_rows(layout.angles_rad(device=m.device, dtype=torch.float64))  # (4, 3) site order
    out = torch.einsum("kc,...chw->...hwk", ideal, s) + residual  # (*, H, W, 4) site order
    order = [2 * i + j for i, j in (layout.site_of_channel(c) for c in range(4))]
    return out[..., order].movedim(-1, -3)
