"""polcal.npz files: round trip, validation, and how a capture references one."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from polarshape.errors import CaptureError, OutputExistsError
from polarshape.imaging.analyser import PolarimetricCalibration
from polarshape.imaging.mosaic import MosaicLayout
from polarshape.io.polarimetric import (
    capture_polarimetric_calibration,
    read_polarimetric_calibration,
    write_polarimetric_calibration,
)


def _cal() -> PolarimetricCalibration:
    ideal = PolarimetricCalibration.ideal(MosaicLayout.imx250mzr(), 4, 6, bit_depth=12, black_level=64.0)
    defects = ideal.defects.clone()
    defects[1, 2] = True
    return PolarimetricCalibration(angle_rad=ideal.angle_rad + 0.01, diattenuation=ideal.diattenuation * 0.98,
                                   gain=ideal.gain * 1.01, black_level=ideal.black_level + 1.5, defects=defects,
                                   bit_depth=12, info={"angle_error_rms_deg": 1.2, "note": "é"})


def test_round_trip_and_overwrite(tmp_path: Path) -> None:
    cal = _cal()
    path = write_polarimetric_calibration(tmp_path / "polcal.npz", cal)
    back = read_polarimetric_calibration(path, expect_shape=(4, 6))
    for name in ("angle_rad", "diattenuation", "gain", "black_level", "defects"):
        assert torch.equal(getattr(back, name), getattr(cal, name))
    assert back.bit_depth == 12 and back.info == cal.info
    with pytest.raises(OutputExistsError):
        write_polarimetric_calibration(path, cal)
    write_polarimetric_calibration(path, cal, overwrite=True)
    with pytest.raises(ValueError, match=".npz"):
        write_polarimetric_calibration(tmp_path / "polcal.npy", cal)
    assert [p.name for p in tmp_path.iterdir()] == ["polcal.npz"]  # nothing half-written left


def test_read_errors(tmp_path: Path) -> None:
    path = write_polarimetric_calibration(tmp_path / "polcal.npz", _cal())
    with pytest.raises(CaptureError, match="not found"):
        read_polarimetric_calibration(tmp_path / "missing.npz")
    with pytest.raises(CaptureError, match="6×4 \\(W×H\\) frames but the capture's frames are 8×4"):
        read_polarimetric_calibration(path, expect_shape=(4, 8))
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(CaptureError, match="cannot be read"):
        read_polarimetric_calibration(tmp_path / "junk.npz")
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    np.savez(tmp_path / "old.npz", **{**arrays, "meta": np.array(json.dumps({"format": "polarshape-polcal/0"}))})
    with pytest.raises(CaptureError, match="format"):
        read_polarimetric_calibration(tmp_path / "old.npz")
    np.savez(tmp_path / "partial.npz", **{k: v for k, v in arrays.items() if k != "gain"})
    with pytest.raises(CaptureError, match="missing gain"):
        read_polarimetric_calibration(tmp_path / "partial.npz")
    bad = dict(arrays, gain=np.full(arrays["gain"].shape, math.nan))
    np.savez(tmp_path / "nan.npz", **bad)
    with pytest.raises(CaptureError, match="NaN"):
        read_polarimetric_calibration(tmp_path / "nan.npz")


def test_capture_reference(tmp_path: Path) -> None:
    from polarshape.io.capture import load_capture

    capture = _capture(tmp_path)
    assert capture_polarimetric_calibration(capture) is None
    write_polarimetric_calibration(tmp_path / "cap" / "polcal.npz", _cal())
    yaml_path = tmp_path / "cap" / "capture.yaml"
    text = yaml_path.read_text().replace("camera:\n", "camera:\n  polarimetric_calibration: polcal.npz\n", 1)
    yaml_path.write_text(text)
    loaded = load_capture(tmp_path / "cap")
    assert loaded.spec.camera.polarimetric_calibration == "polcal.npz"
    cal = capture_polarimetric_calibration(loaded)
    assert cal is not None and cal.shape == (4, 6)
    yaml_path.write_text(text.replace("polcal.npz", "other.npz"))
    with pytest.raises(CaptureError, match="camera.polarimetric_calibration in capture.yaml .*not found"):
        capture_polarimetric_calibration(load_capture(tmp_path / "cap"))


def _capture(tmp_path: Path):  # noqa: ANN202
    from polarshape.io.capture import Capture, CaptureSpec, load_capture, write_capture

    spec = CaptureSpec.model_validate({
        "format": "polarshape-capture/1",
        "camera": {"projection": "orthographic", "bit_depth": 12, "black_level": 64},
        "lights": [{"direction": [0, 0, -1], "frame": "frames/000.png"}],
    })
    frames = np.full((1, 4, 6), 1000, dtype=np.uint16)
    return load_capture(write_capture(tmp_path / "cap", Capture(spec=spec, frames=frames)))
