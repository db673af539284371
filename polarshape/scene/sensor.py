"""Sensor model of the simulator: radiance → electrons → noisy, clipped, quantised counts.

Per pixel (spec fmbrdf.md §8):

1. mean signal ``λ = max(radiance, 0) · electrons_per_radiance · exposure_us / reference_exposure_us``
   electrons;
2. shot noise: ``Poisson(λ)`` (or its Gaussian approximation ``λ + √λ·N(0, 1)``, or none);
3. saturation of the photodiode at ``full_well_e``;
4. read noise ``read_noise_e · N(0, 1)`` electrons;
5. conversion ``counts = e / e_per_count + black_level`` (+ a hot pixel's dark signal,
   :mod:`polarshape.scene.sensor_defects`); the conversion factor at bit depth b and
   gain g dB is ``e_per_count_12bit · 2^(12 − b) / 10^(g / 20)`` (the ADC is 12-bit: 8-bit formats
   drop 4 bits, 16-bit ones shift 4 bits up) and the black level scales the same way;
6. rounding to integers and clipping to ``[0, 2^b − 1]`` (ADC saturation).

Randomness comes only from the ``torch.Generator`` passed in, so a seed reproduces a frame
bit-exactly (on one device and torch version).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from polarshape.imaging.pixels import check_bit_depth, max_count
from polarshape.checks import to_numpy

__all__ = ["SensorModel", "ShotNoise"]

ShotNoise = Literal["poisson", "gaussian", "none"]


@dataclass(frozen=True)
class SensorModel:
    """Noise and conversion parameters (defaults close to a Sony IMX250MZR).

    Attributes:
        full_well_e: photodiode capacity, electrons.
        read_noise_e: read noise, electrons rms (0 = none).
        e_per_count_12bit: electrons per 12-bit count at 0 dB; None = full well maps to the top
            count (``full_well_e / (4095 − black_level_12bit)``).
        black_level_12bit: dark offset in 12-bit counts.
        electrons_per_radiance: electrons collected from radiance 1 during the reference exposure.
        reference_exposure_us: exposure time at which ``electrons_per_radiance`` holds, µs.
        shot_noise: ``poisson`` (exact), ``gaussian`` (approximation, fine for λ ≳ 20) or ``none``.
    """

    full_well_e: float = 10500.0
    read_noise_e: float = 2.5
    e_per_count_12bit: float | None = None
    black_level_12bit: float = 0.0
    electrons_per_radiance: float = 80000.0
    reference_exposure_us: float = 10000.0
    shot_noise: ShotNoise = "poisson"

    def __post_init__(self) -> None:
        checks = {
            "full_well_e": self.full_well_e > 0,
            "read_noise_e": self.read_noise_e >= 0,
            "black_level_12bit": 0 <= self.black_level_12bit < 4095,
            "electrons_per_radiance": self.electrons_per_radiance > 0,
            "reference_exposure_us": self.reference_exposure_us > 0,
            "e_per_count_12bit": self.e_per_count_12bit is None or self.e_per_count_12bit > 0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"sensor.{name} is out of range: {getattr(self, name)!r}")
        if self.shot_noise not in ("poisson", "gaussian", "none"):
            raise ValueError(f"sensor.shot_noise must be poisson, gaussian or none, got {self.shot_noise!r}")

    def e_per_count(self, bit_depth: int, gain_db: float = 0.0) -> float:
        """Electrons per count at ``bit_depth`` and analogue gain ``gain_db``."""
        check_bit_depth(bit_depth)
        base = self.e_per_count_12bit
        if base is None:
            base = self.full_well_e / (4095.0 - self.black_level_12bit)
        return base * 2.0 ** (12 - bit_depth) / 10.0 ** (gain_db / 20.0)

    def black_level(self, bit_depth: int) -> float:
        """Black level in counts of ``bit_depth``."""
        check_bit_depth(bit_depth)
        return self.black_level_12bit * 2.0 ** (bit_depth - 12)

    def full_scale_per_radiance(self, exposure_us: float, gain_db: float = 0.0, bit_depth: int = 12) -> float:
        """Fraction of full scale (above the black level) that radiance 1 gives at this exposure and gain:
        electrons per radiance × exposure / (electrons per count × (top count − black level)).

        It is the capture's albedo units per physical albedo — what a white reference target of albedo 1
        would measure (``interreflection.albedo_scale``; the "true" albedos of the report).
        """
        electrons = self.electrons_per_radiance * exposure_us / self.reference_exposure_us
        return electrons / self.e_per_count(bit_depth, gain_db) / (max_count(bit_depth) - self.black_level(bit_depth))

    def mean_electrons(self, radiance: Tensor, exposure_us: float) -> Tensor:
        """Expected electrons (…) for radiance (…) during ``exposure_us``."""
        if not exposure_us > 0:
            raise ValueError(f"exposure_us must be > 0, got {exposure_us}")
        return radiance.clamp_min(0.0) * (self.electrons_per_radiance * exposure_us / self.reference_exposure_us)

    def expose(
        self,
        radiance: Tensor,
        *,
        exposure_us: float,
        gain_db: float = 0.0,
        bit_depth: int = 12,
        generator: torch.Generator | None = None,
        dark_counts_12bit: Tensor | None = None,
    ) -> np.ndarray:
        """Counts of one exposure.

        Args:
            radiance: (H, W) (or any shape) radiance behind the polarisers, float tensor on any
                device.
            exposure_us: exposure time, µs.
            gain_db: analogue gain, dB.
            bit_depth: 8, 10, 12 or 16.
            generator: random source on ``radiance.device`` (None: torch's global generator,
                not reproducible).
            dark_counts_12bit: (H, W) extra per-pixel dark signal in 12-bit counts (hot pixels,
                :mod:`polarshape.scene.sensor_defects`), scaled to ``bit_depth`` like the black
                level; None = none.

        Returns:
            Same shape, ``uint8`` for 8 bits else ``uint16``, low-bit aligned counts.
        """
        check_bit_depth(bit_depth)
        if not math.isfinite(gain_db):
            raise ValueError(f"gain_db must be finite, got {gain_db}")
        if not radiance.is_floating_point():
            raise TypeError(f"radiance must be a floating-point tensor, got {radiance.dtype}")
        work = radiance.to(torch.float32 if radiance.device.type == "mps" else torch.float64)  # mps has no float64
        electrons = self.mean_electrons(work, exposure_us)
        if self.shot_noise == "poisson":
            electrons = torch.poisson(electrons, generator=generator)
        elif self.shot_noise == "gaussian":
            electrons = electrons + electrons.sqrt() * _normal_like(electrons, generator)
        electrons = electrons.clamp_max(self.full_well_e)
        if self.read_noise_e > 0:
            electrons = electrons + self.read_noise_e * _normal_like(electrons, generator)
        counts = electrons / self.e_per_count(bit_depth, gain_db) + self.black_level(bit_depth)
        if dark_counts_12bit is not None:
            counts = counts + dark_counts_12bit.to(counts) * 2.0 ** (bit_depth - 12)
        counts = torch.round(counts).clamp(0, max_count(bit_depth))
        return to_numpy(counts, np.uint8 if bit_depth == 8 else np.uint16)


def _normal_like(x: Tensor, generator: torch.Generator | None) -> Tensor:
    return torch.randn(x.shape, dtype=x.dtype, device=x.device, generator=generator)
