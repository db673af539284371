"""The simulated sensor's imperfections: per-pixel analysers, PRNU, hot and dead pixels (issue 16).

A real division-of-focal-plane sensor is not the ideal IMX250MZR of spec §1: every micro-polariser's
axis is a little off its nominal angle, it leaks some light polarised across it (finite extinction
ratio), pixels differ in response (photo-response non-uniformity, PRNU) and a few are hot (a large
dark signal) or dead (no response). :class:`SensorDefects` holds the scene's ``sensor:`` values
(defaults: the ideal sensor) and :meth:`SensorDefects.draw` turns them into :class:`SensorMaps`, one
value per raw pixel, drawn once from ``defects_seed`` — a property of the camera, the same for every
frame, for every light and for the calibration frames. The maps enter the forward model only through
:func:`polarshape.imaging.analyser.analysed_intensity` (the one analyser formula) and a per-pixel dark
offset of :meth:`polarshape.scene.sensor.SensorModel.expose`; :meth:`SensorMaps.to_calibration`
exposes them as the :class:`~polarshape.imaging.analyser.PolarimetricCalibration` a perfect bench
calibration would find.

Per pixel (nominal angle θ₀ of its layout site):

- angle ``θ = θ₀ + N(0, analyser_angle_error_deg)``;
- extinction ratio ``ER = extinction_ratio · exp(extinction_ratio_spread · N(0, 1))`` (None: ER = ∞),
  diattenuation ``D = (ER − 1) / (ER + 1)``;
- gain ``g = 1 + prnu · N(0, 1)`` (dead pixels: 0);
- hot pixels (exactly ``round(hot_pixel_fraction · N)`` of them): a constant dark signal uniform in
  [½, 1) of the 12-bit full scale above the black level (they saturate with light on them);
- dead pixels (``round(dead_pixel_fraction · N)``, disjoint from the hot ones): no response.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from polarshape.imaging.analyser import PolarimetricCalibration, diattenuation_from_extinction
from polarshape.imaging.mosaic import MosaicLayout

__all__ = ["SensorDefects", "SensorMaps"]

#: Hot pixels' dark signal lies in [HOT_LEVEL_RANGE[0], HOT_LEVEL_RANGE[1]) of the 12-bit full scale.
HOT_LEVEL_RANGE = (0.5, 1.0)


@dataclass(frozen=True)
class SensorDefects:
    """The imperfect-sensor fields of a scene's ``sensor:`` section (module docstring); the defaults
    are the ideal sensor.

    Attributes:
        analyser_angle_error_deg: σ of each pixel's polariser-axis error, degrees (0 = exact).
        extinction_ratio: mean extinction ratio t_max / t_min (> 1); None = infinite (perfect).
        extinction_ratio_spread: σ of log ER across pixels (0 = every pixel ``extinction_ratio``).
        prnu: σ of each pixel's relative gain (photo-response non-uniformity), e.g. 0.01 = 1 %.
        hot_pixel_fraction: fraction of hot pixels, in [0, 0.5).
        dead_pixel_fraction: fraction of dead pixels, in [0, 0.5).
        defects_seed: seed of the per-pixel maps (the camera's; not the noise seed).
    """

    analyser_angle_error_deg: float = 0.0
    extinction_ratio: float | None = None
    extinction_ratio_spread: float = 0.0
    prnu: float = 0.0
    hot_pixel_fraction: float = 0.0
    dead_pixel_fraction: float = 0.0
    defects_seed: int = 0

    def __post_init__(self) -> None:
        self.check_defects()

    def check_defects(self) -> None:
        """Raise ValueError naming the ``sensor.<field>`` out of range."""
        er = self.extinction_ratio
        checks = {
            "analyser_angle_error_deg": 0 <= self.analyser_angle_error_deg <= 10,
            "extinction_ratio": er is None or (math.isfinite(er) and er > 1),
            "extinction_ratio_spread": 0 <= self.extinction_ratio_spread <= 2,
            "prnu": 0 <= self.prnu <= 0.2,
            "hot_pixel_fraction": 0 <= self.hot_pixel_fraction < 0.5,
            "dead_pixel_fraction": 0 <= self.dead_pixel_fraction < 0.5,
        }
        hints = {
            "analyser_angle_error_deg": "a σ in degrees within [0, 10]",
            "extinction_ratio": "a number > 1 (e.g. 150 for 150:1), or null for a perfect polariser",
            "extinction_ratio_spread": "σ of log ER within [0, 2]",
            "prnu": "σ of the relative gain within [0, 0.2] (0.01 = 1 %)",
            "hot_pixel_fraction": "a fraction in [0, 0.5), e.g. 0.0002 for 0.02 %",
            "dead_pixel_fraction": "a fraction in [0, 0.5), e.g. 0.0001",
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"sensor.{name} is out of range: {getattr(self, name)!r}; give {hints[name]}")
        if self.extinction_ratio is None and self.extinction_ratio_spread > 0:
            raise ValueError("sensor.extinction_ratio_spread needs sensor.extinction_ratio (a number > 1)")
        if self.hot_pixel_fraction + self.dead_pixel_fraction >= 0.5:
            raise ValueError("sensor.hot_pixel_fraction + sensor.dead_pixel_fraction must stay below 0.5")

    def defects_only(self) -> SensorDefects:
        """These fields alone (for a subclass such as the scene's ``SensorConfig``)."""
        return SensorDefects(
            analyser_angle_error_deg=self.analyser_angle_error_deg, extinction_ratio=self.extinction_ratio,
            extinction_ratio_spread=self.extinction_ratio_spread, prnu=self.prnu,
            hot_pixel_fraction=self.hot_pixel_fraction, dead_pixel_fraction=self.dead_pixel_fraction,
            defects_seed=self.defects_seed,
        )

    @property
    def is_ideal(self) -> bool:
        """True when every imperfection is off (the frames are those of the ideal sensor)."""
        return (self.analyser_angle_error_deg == 0 and self.extinction_ratio is None and self.prnu == 0
                and self.hot_pixel_fraction == 0 and self.dead_pixel_fraction == 0)

    def draw(self, layout: MosaicLayout, height: int, width: int) -> SensorMaps:
        """The per-pixel maps of a (height, width) raw mosaic (even sides), from ``defects_seed``.

        Drawn on the CPU in float64 with a generator of its own (so a seed gives the same camera on
        every device); move them with :meth:`SensorMaps.to`.
        """
        ideal = PolarimetricCalibration.ideal(layout, height, width, bit_depth=12)
        gen = torch.Generator(device="cpu")
        gen.manual_seed(int(self.defects_seed))
        shape = (height, width)
        n = height * width
        # draw every map whatever its σ, so one field's value does not change another's pixels
        angle_noise = torch.randn(shape, dtype=torch.float64, generator=gen)
        er_noise = torch.randn(shape, dtype=torch.float64, generator=gen)
        gain_noise = torch.randn(shape, dtype=torch.float64, generator=gen)
        order = torch.randperm(n, generator=gen)
        hot_u = torch.rand(shape, dtype=torch.float64, generator=gen)
        angle = ideal.angle_rad + math.radians(self.analyser_angle_error_deg) * angle_noise
        if self.extinction_ratio is None:
            diattenuation = torch.ones(shape, dtype=torch.float64)
        else:
            er = self.extinction_ratio * torch.exp(self.extinction_ratio_spread * er_noise)
            diattenuation = diattenuation_from_extinction(er.clamp_min(1.0 + 1e-6))
        gain = (1.0 + self.prnu * gain_noise).clamp_min(1e-3)
        n_hot = int(round(self.hot_pixel_fraction * n))
        n_dead = int(round(self.dead_pixel_fraction * n))
        hot = torch.zeros(n, dtype=torch.bool)
        hot[order[:n_hot]] = True
        dead = torch.zeros(n, dtype=torch.bool)
        dead[order[n_hot:n_hot + n_dead]] = True
        hot, dead = hot.reshape(shape), dead.reshape(shape)
        lo, hi = HOT_LEVEL_RANGE
        hot_level = torch.where(hot, 4095.0 * (lo + (hi - lo) * hot_u), torch.zeros_like(hot_u))
        gain = torch.where(dead, torch.zeros_like(gain), gain)
        return SensorMaps(angle_rad=angle, diattenuation=diattenuation, gain=gain, hot=hot, dead=dead,
                          hot_level_12bit=hot_level)


@dataclass(frozen=True)
class SensorMaps:
    """One sensor's per-pixel truth at raw-mosaic resolution (2H, 2W).

    Attributes:
        angle_rad: (2H, 2W) analyser axis, radians, our convention.
        diattenuation: (2H, 2W) D in (0, 1].
        gain: (2H, 2W) relative response (0 on dead pixels).
        hot: (2H, 2W) bool hot pixels.
        dead: (2H, 2W) bool dead pixels.
        hot_level_12bit: (2H, 2W) extra dark signal in 12-bit counts (0 off the hot pixels).
    """

    angle_rad: Tensor
    diattenuation: Tensor
    gain: Tensor
    hot: Tensor
    dead: Tensor
    hot_level_12bit: Tensor

    def to(self, device: torch.device | str, dtype: torch.dtype) -> SensorMaps:
        """The maps on ``device`` (float maps in ``dtype``, masks stay bool)."""
        return SensorMaps(
            angle_rad=self.angle_rad.to(device=device, dtype=dtype),
            diattenuation=self.diattenuation.to(device=device, dtype=dtype),
            gain=self.gain.to(device=device, dtype=dtype),
            hot=self.hot.to(device), dead=self.dead.to(device),
            hot_level_12bit=self.hot_level_12bit.to(device=device, dtype=dtype),
        )

    def to_calibration(self, *, bit_depth: int, black_level: float, info: dict | None = None) -> PolarimetricCalibration:
        """The :class:`PolarimetricCalibration` of this sensor (the truth a calibration should find).

        Args:
            bit_depth: bit depth of the counts ``black_level`` is in.
            black_level: the sensor's uniform black level in counts of ``bit_depth``.
            info: stored with it.

        Dead pixels keep gain 1 in the file (they are flagged in ``defects``); hot pixels' black
        level is their dark level.
        """
        scale = 2.0 ** (bit_depth - 12)
        black = float(black_level) + self.hot_level_12bit.double().cpu() * scale
        defects = (self.hot | self.dead).cpu()
        gain = torch.where(self.dead.cpu(), torch.ones_like(self.gain, device="cpu"), self.gain.double().cpu())
        return PolarimetricCalibration(
            angle_rad=self.angle_rad.double().cpu(), diattenuation=self.diattenuation.double().cpu(),
            gain=gain.double(), black_level=black, defects=defects, bit_depth=int(bit_depth),
            info=dict(info or {}),
        )
