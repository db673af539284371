"""Preprocessing a capture whose capture.yaml references a polarimetric calibration."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from polarshape.errors import CaptureError
from polarshape.imaging.analyser import PolarimetricCalibration, analysed_intensity, diattenuation_from_extinction
from polarshape.imaging.mosaic import MosaicLayout
from polarshape.io.capture import Capture, CaptureSpec, load_capture, write_capture
from polarshape.io.polarimetric import write_polarimetric_calibration
from polarshape.recover.preprocess import preprocess_capture

LAYOUT = MosaicLayout.imx250mzr()
H2, W2 = 32, 32
TOP = 4095.0
BLACK = 64.0


def _sensor(defects: list[tuple[int, int]]) -> PolarimetricCalibration:
    g = torch.Generator().manual_seed(0)
    ideal = PolarimetricCalibration.ideal(LAYOUT, H2, W2, bit_depth=12, black_level=BLACK)
    mask = torch.zeros(H2, W2, dtype=torch.bool)
    for y, x in defects:
        mask[y, x] = True
    return PolarimetricCalibration(
        angle_rad=ideal.angle_rad + math.radians(3.0) * torch.randn(H2, W2, generator=g, dtype=torch.float64),
        diattenuation=torch.full((H2, W2), float(diattenuation_from_extinction(50.0))),
        gain=1.0 + 0.05 * torch.randn(H2, W2, generator=g, dtype=torch.float64),
        black_level=BLACK + torch.randint(-3, 4, (H2, W2), generator=g).double(), defects=mask, bit_depth=12,
    )


def _truth(k: int, uniform: bool = False) -> torch.Tensor:
    """(K, 3, H, W) Stokes constant over each block (``uniform``: over the frame): s0 0.3–0.6, DoLP 0.1."""
    y, x = torch.meshgrid(torch.arange(H2 // 2), torch.arange(W2 // 2), indexing="ij")
    if uniform:
        x, y = torch.full_like(x, 3), torch.full_like(y, 5)
    out = []
    for i in range(k):
        s0 = 0.3 + 0.3 * (x + y + i).double() / (H2 + W2)
        ang = 0.1 * x.double() + 0.05 * y.double() + i
        out.append(torch.stack([s0, 0.1 * s0 * torch.cos(2 * ang), 0.1 * s0 * torch.sin(2 * ang)]))
    return torch.stack(out)


def _capture(tmp_path: Path, sensor: PolarimetricCalibration, *, reference: str | None,
             uniform: bool = False) -> Capture:
    truth = _truth(4, uniform)
    full = truth.repeat_interleave(2, -1).repeat_interleave(2, -2)  # (K, 3, 2H, 2W)
    clean = analysed_intensity(full, sensor.angle_rad, sensor.diattenuation, sensor.gain) * (TOP - BLACK)
    counts = sensor.black_level + clean
    counts = torch.where(sensor.defects, torch.full_like(counts, TOP), counts)  # hot pixels stuck at the top
    frames = np.clip(np.rint(counts.numpy()), 0, TOP).astype(np.uint16)
    camera = {"projection": "orthographic", "bit_depth": 12, "black_level": BLACK}
    if reference is not None:
        camera["polarimetric_calibration"] = reference
    spec = CaptureSpec.model_validate({
        "format": "polarshape-capture/1", "camera": camera,
        "lights": [{"direction": [0.3 * math.cos(i) / 1.044031, 0.3 * math.sin(i) / 1.044031, -1.0 / 1.044031], "frame": f"frames/{i:03d}.png"}
                   for i in range(4)],
    })
    root = write_capture(tmp_path / "cap", Capture(spec=spec, frames=frames))
    write_polarimetric_calibration(tmp_path / "cap" / "polcal.npz", sensor, overwrite=True)
    return load_capture(root)


@pytest.mark.parametrize("demosaic", ["superpixel", "bilinear"])
def test_calibrated_capture_recovers_the_stokes_vectors(tmp_path: Path, demosaic: str) -> None:
    sensor = _sensor(defects=[(4, 4), (10, 10), (10, 11)])  # block (2, 2): one defect; block (5, 5): two
    uniform = demosaic == "bilinear"  # it interpolates across blocks: exact for a uniform field
    truth = _truth(4, uniform)
    kw = {"dtype": torch.float64, "demosaic": demosaic, "mixed_sigma": None, "polarisation_check": False}
    cal = preprocess_capture(_capture(tmp_path / "a", sensor, reference="polcal.npz", uniform=uniform), **kw)
    raw = preprocess_capture(_capture(tmp_path / "b", sensor, reference=None, uniform=uniform), **kw)
    assert not bool(cal.valid[:, 5, 5].any())  # two defects: no Stokes vector
    assert bool(cal.valid[:, 2, 2].all())  # one defect: three sites suffice
    err_cal = (cal.stokes - truth).abs().amax(1)[cal.valid]
    err_raw = (raw.stokes - truth).abs().amax(1)[cal.valid & raw.valid]
    assert float(err_cal.max()) < 1e-3  # quantisation (≈ 1e-4 of full scale)
    assert float(err_raw.median()) > 10 * float(err_cal.median())


def test_missing_or_mismatched_calibration(tmp_path: Path) -> None:
    sensor = _sensor(defects=[])
    capture = _capture(tmp_path, sensor, reference="elsewhere/polcal.npz")
    with pytest.raises(CaptureError, match="camera.polarimetric_calibration in capture.yaml.*not found"):
        preprocess_capture(capture, polarisation_check=False)
    small = PolarimetricCalibration.ideal(LAYOUT, 8, 8, bit_depth=12)
    write_polarimetric_calibration(tmp_path / "small.npz", small)
    capture = _capture(tmp_path / "c", sensor, reference=str(tmp_path / "small.npz"))
    with pytest.raises(CaptureError, match="camera.polarimetric_calibration.*8×8"):
        preprocess_capture(capture, polarisation_check=False)


def test_calibrated_exposure_brackets_merge_before_the_analysers(tmp_path: Path) -> None:
    """Format 2 with a calibration: each frame loses its per-pixel black level before merging, so the
    merged Stokes vectors are the truth at the reference exposure, also where the reference clipped."""
    sensor = _sensor(defects=[(4, 4)])
    g = torch.Generator().manual_seed(1)  # a black level varying by ±40 counts: a misplaced shift shows
    sensor = dataclasses.replace(sensor, black_level=BLACK + torch.randint(-40, 41, (H2, W2), generator=g).double())
    truth = _truth(4) * 4.0  # s0 1.2–2.4 of the reference's full scale: clipped at the reference
    ratios = (1.0, 0.25, 0.0625)
    frames = []
    for r in ratios:
        full = (truth * r).repeat_interleave(2, -1).repeat_interleave(2, -2)
        counts = sensor.black_level + analysed_intensity(full, sensor.angle_rad, sensor.diattenuation, sensor.gain) * (TOP - BLACK)
        counts = torch.where(sensor.defects, torch.full_like(counts, TOP), counts)
        frames.append(np.clip(np.rint(counts.numpy()), 0, TOP).astype(np.uint16))
    spec = CaptureSpec.model_validate({
        "format": "polarshape-capture/2",
        "camera": {"projection": "orthographic", "bit_depth": 12, "black_level": BLACK,
                   "polarimetric_calibration": "polcal.npz"},
        "lights": [{"direction": [0.3 * math.cos(i) / 1.044031, 0.3 * math.sin(i) / 1.044031, -1.0 / 1.044031],
                    "frame": f"frames/{i:03d}.png", "exposure_us": 8000.0,
                    "brackets": [{"frame": f"frames/{i:03d}_b{j}.png", "exposure_us": 8000.0 * r}
                                 for j, r in enumerate(ratios[1:], 1)]} for i in range(4)],
    })
    root = write_capture(tmp_path / "cap", Capture(spec=spec, frames=frames[0],
                                                   brackets=np.stack(frames[1:], axis=1)))
    write_polarimetric_calibration(root / "polcal.npz", sensor, overwrite=True)
    inputs = preprocess_capture(load_capture(root), dtype=torch.float64, demosaic="superpixel", mixed_sigma=None,
                                polarisation_check=False)
    assert int(inputs.saturated.sum()) == 0
    ok = inputs.valid
    err = (inputs.stokes - truth).abs().amax(1)[ok]  # (N,) worst of s0, s1, s2
    assert int(ok.sum()) > 0.9 * ok.numel() and float(err.max()) < 0.01 and float(err.median()) < 0.002
