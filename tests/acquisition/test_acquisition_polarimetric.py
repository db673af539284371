"""Estimation of a polarimetric calibration from synthetic bench frames (dark, flat, polariser series)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polarshape.acquisition.polarimetric import estimate_polarimetric_calibration
from polarshape.imaging.analyser import analysed_intensity, diattenuation_from_extinction
from polarshape.imaging.mosaic import MosaicLayout

LAYOUT = MosaicLayout.imx250mzr()
TOP = 4095.0  # 12-bit


def make_sensor(size: int = 32, *, sigma_deg: float = 1.5, extinction: float = 150.0, prnu: float = 0.01,
                black: float = 64.0, n_hot: int = 3, n_dead: int = 2, seed: int = 0) -> dict[str, np.ndarray]:
    """A random imperfect sensor of size × size raw pixels: true θ, D, g, black, hot and dead pixels."""
    rng = np.random.default_rng(seed)
    nominal = np.tile(np.radians(np.array(LAYOUT.angles_deg)), (size // 2, size // 2))
    theta = nominal + np.radians(sigma_deg) * rng.standard_normal((size, size))
    er = extinction * np.exp(0.05 * rng.standard_normal((size, size)))
    d = diattenuation_from_extinction(torch.from_numpy(er)).numpy()
    g = 1.0 + prnu * rng.standard_normal((size, size))
    b = black + 0.5 * rng.standard_normal((size, size))
    hot = np.zeros((size, size), bool)
    dead = np.zeros((size, size), bool)
    flat_idx = rng.choice(size * size, n_hot + n_dead, replace=False)
    hot.flat[flat_idx[:n_hot]] = True
    dead.flat[flat_idx[n_hot:]] = True
    b = np.where(hot, b + 400.0, b)
    g = np.where(dead, 0.02, g)
    return {"theta": theta, "d": d, "g": g, "black": b, "hot": hot, "dead": dead}


def expose(sensor: dict[str, np.ndarray], stokes: np.ndarray, n: int, *, rng: np.random.Generator,
           read_noise: float = 2.0, average: int = 1) -> np.ndarray:
    """n frames (n, 2H, 2W) uint16 of a uniform Stokes vector (3,) in fractions of full scale, shot +
    read noise (``average`` frames averaged per frame: noise / √average)."""
    size = sensor["theta"].shape[0]
    s = torch.from_numpy(np.broadcast_to(np.asarray(stokes, float)[:, None, None], (3, size, size)).copy())
    clean = analysed_intensity(s, torch.from_numpy(sensor["theta"]), torch.from_numpy(sensor["d"]),
                               torch.from_numpy(sensor["g"])).numpy() * (TOP - 64.0)
    out = []
    for _ in range(n):
        sigma = np.sqrt(np.maximum(clean, 0) * 1.0 + read_noise**2) / math.sqrt(average)  # gain 1 e-/count
        counts = sensor["black"] + clean + sigma * rng.standard_normal(clean.shape)
        out.append(np.clip(np.rint(counts), 0, TOP))
    return np.stack(out).astype(np.uint16)


def bench(sensor: dict[str, np.ndarray], *, n_angles: int = 12, offset_deg: float = 3.0, average: int = 16,
          level: float = 0.8, seed: int = 1) -> dict[str, object]:
    """Dark, flat and polariser frames; angles in the makers' convention with a mount offset."""
    rng = np.random.default_rng(seed)
    ours = np.arange(n_angles) * 180.0 / n_angles  # the polariser's true angle (ours)
    pol = np.concatenate([
        expose(sensor, level * np.array([1.0, math.cos(math.radians(2 * a)), math.sin(math.radians(2 * a))]), 1,
               rng=rng, average=average) for a in ours
    ])
    labels = [(-a + offset_deg) % 360 for a in ours]  # maker convention: our −a, mount zero off by offset
    return {
        "polariser": pol, "angles_deg": labels,
        "flat": expose(sensor, np.array([level, 0.0, 0.0]), 32, rng=rng, average=average),
        "dark": expose(sensor, np.zeros(3), 8, rng=rng),
    }


def test_recovers_angles_extinction_gain_black_defects() -> None:
    sensor = make_sensor()
    frames = bench(sensor)
    cal = estimate_polarimetric_calibration(layout=LAYOUT, bit_depth=12, **frames)  # type: ignore[arg-type]
    truth_defects = sensor["hot"] | sensor["dead"]
    assert np.array_equal(cal.defects.numpy(), truth_defects)
    good = ~truth_defects
    err = np.degrees(cal.angle_rad.numpy() - sensor["theta"])[good]
    err -= err.mean()  # the global rotation is not observable with a relative mount
    assert math.sqrt(float(np.mean(err**2))) <= 0.2
    er = cal.extinction_ratio().numpy()[good]
    assert abs(np.median(er) / 150.0 - 1) <= 0.10
    g_true = sensor["g"][good] / sensor["g"][good].mean()
    assert float(np.sqrt(np.mean((cal.gain.numpy()[good] - g_true) ** 2))) <= 0.002
    assert float(np.sqrt(np.mean((cal.black_level.numpy() - sensor["black"])[good] ** 2))) <= 1.0  # 8 frames, σ 2
    assert cal.info["hot"] == 3 and cal.info["dead"] == 2
    # maker labels +3° off: ψ given = true ψ − 3°, so the analysers come out 3° behind (removed, recorded)
    assert cal.info["mount_offset_deg"] == pytest.approx(-3.0, abs=0.3)
    assert cal.info["angle_error_rms_deg"] == pytest.approx(1.5, abs=0.3)


def test_absolute_angles_keep_the_offset() -> None:
    sensor = make_sensor(sigma_deg=0.5, n_hot=0, n_dead=0)
    frames = bench(sensor, offset_deg=0.0, n_angles=8)
    cal = estimate_polarimetric_calibration(layout=LAYOUT, bit_depth=12, absolute_angles=True, **frames)  # type: ignore[arg-type]
    err = np.degrees(cal.angle_rad.numpy() - sensor["theta"])
    assert abs(float(err.mean())) < 0.1 and float(np.sqrt(np.mean(err**2))) < 0.3


def test_without_flat_and_dark_gain_from_fit() -> None:
    sensor = make_sensor(black=0.0, n_hot=0, n_dead=0)
    frames = bench(sensor)
    cal = estimate_polarimetric_calibration(layout=LAYOUT, bit_depth=12, polariser=frames["polariser"],  # type: ignore[arg-type]
                                            angles_deg=frames["angles_deg"], black_level=0.0)  # type: ignore[arg-type]
    g_true = sensor["g"] / sensor["g"].mean()
    assert float(np.sqrt(np.mean((cal.gain.numpy() - g_true) ** 2))) <= 0.003
    assert cal.info["gain_from"] == "polariser fit"


def _frames() -> dict[str, object]:
    return bench(make_sensor(size=16, n_hot=0, n_dead=0), n_angles=6)


def test_errors_name_the_problem() -> None:
    f = _frames()
    pol, angles = f["polariser"], f["angles_deg"]
    with pytest.raises(ValueError, match="≥ 3 angles"):
        estimate_polarimetric_calibration(polariser=pol[:2], angles_deg=angles[:2], layout=LAYOUT, bit_depth=12)  # type: ignore[index]
    with pytest.raises(ValueError, match="5 angles for 6"):
        estimate_polarimetric_calibration(polariser=pol, angles_deg=angles[:5], layout=LAYOUT, bit_depth=12)  # type: ignore[index,arg-type]
    with pytest.raises(ValueError, match="above 255"):
        estimate_polarimetric_calibration(polariser=pol, angles_deg=angles, layout=LAYOUT, bit_depth=8)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="different exposures"):
        mixed = np.array(pol, dtype=np.int64)
        mixed[0] = (mixed[0] - 64) // 4 + 64
        estimate_polarimetric_calibration(polariser=mixed, angles_deg=angles, layout=LAYOUT, bit_depth=12)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="different exposures"):
        flat = np.array(f["flat"], dtype=np.int64)
        flat[1] = (flat[1] - 64) // 2 + 64
        estimate_polarimetric_calibration(polariser=pol, angles_deg=angles, flat=flat, layout=LAYOUT, bit_depth=12)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="same camera, ROI"):
        estimate_polarimetric_calibration(polariser=pol, angles_deg=angles, dark=np.asarray(f["dark"])[:, :8],  # type: ignore[arg-type]
                                          layout=LAYOUT, bit_depth=12)
    with pytest.raises(ValueError, match="does not modulate|barely change"):
        flat = np.asarray(f["flat"])
        estimate_polarimetric_calibration(polariser=np.concatenate([flat[:3], flat[:3]]), angles_deg=angles,  # type: ignore[arg-type]
                                          layout=LAYOUT, bit_depth=12)
    with pytest.raises(ValueError, match="angle-convention clockwise_on_screen"):
        estimate_polarimetric_calibration(polariser=pol, angles_deg=[-a for a in angles],  # type: ignore[attr-defined]
                                          layout=LAYOUT, bit_depth=12)
    with pytest.raises(ValueError, match="not dark frames"):
        estimate_polarimetric_calibration(polariser=pol, angles_deg=angles, dark=f["flat"], layout=LAYOUT, bit_depth=12)  # type: ignore[arg-type]
