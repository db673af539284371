"""`polarshape capture` and `polarshape calibrate` through the command line."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from polarshape.cli import main
from polarshape.io.capture import load_capture

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.usefixtures("require_aravis")
def test_capture_with_fake_gige_camera_writes_a_valid_capture(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cap"
    assert main(["capture", str(REPO / "configs" / "sessions" / "fake_camera.yaml"), "--out", str(out)]) == 0
    assert "capture.yaml" in capsys.readouterr().out
    cap = load_capture(out)
    assert cap.frames.shape == (4, 64, 64) and cap.bit_depth == 12
    assert (cap.frames > 0).any()


@pytest.mark.usefixtures("require_aravis")
def test_capture_with_the_fake_colour_camera_records_the_bayer_pattern(tmp_path: Path) -> None:
    out = tmp_path / "cap"
    assert main(["capture", str(REPO / "configs" / "sessions" / "fake_colour_camera.yaml"), "--out", str(out)]) == 0
    cap = load_capture(out)
    assert cap.frames.shape == (4, 64, 64) and cap.bit_depth == 12 and cap.spec.camera.mosaic.bayer == "RGGB"
    assert cap.spec.camera.model == "TRI050S-QC" and (cap.frames > 0).any()


def test_capture_session_errors_are_reported(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"camera": {"backend": "aravis"}, "rig": {"type": "manual"}, "lights": [{"direction": [0, 0, -1]}]}))
    assert main(["capture", str(bad), "--out", str(tmp_path / "x")]) == 2
    assert "camera.address" in capsys.readouterr().err


def test_calibrate_lights_needs_exactly_one_sphere_outline(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "lights", str(tmp_path / "a.png")]) == 2
    assert "--mask" in capsys.readouterr().err


def test_calibrate_lights_missing_file_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope.png"
    assert main(["calibrate", "lights", str(missing), "--circle", "10", "10", "5"]) == 2
    assert "nope.png" in capsys.readouterr().err


def test_calibrate_lights_mask_sizes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A mask at the images' size or at the super-pixel size (a capture's mask.png) is taken; any other
    size is exit status 2 naming both sizes."""
    yy, xx = np.mgrid[0:64, 0:64]
    sphere = (xx - 31.5) ** 2 + (yy - 31.5) ** 2 < 24**2
    image = np.where(sphere, 200, 0).astype(np.uint16)
    image[20:22, 36:38] = 4000  # the highlight
    cv2.imwrite(str(tmp_path / "a.png"), image)
    superpixel = sphere.reshape(32, 2, 32, 2).mean(axis=(1, 3)) >= 0.5
    cv2.imwrite(str(tmp_path / "mask.png"), superpixel.astype(np.uint8) * 255)
    assert main(["calibrate", "lights", str(tmp_path / "a.png"), "--mask", str(tmp_path / "mask.png")]) == 0
    assert capsys.readouterr().out.startswith("light 0: direction [")
    cv2.imwrite(str(tmp_path / "odd.png"), np.full((40, 40), 255, dtype=np.uint8))
    assert main(["calibrate", "lights", str(tmp_path / "a.png"), "--mask", str(tmp_path / "odd.png")]) == 2
    err = capsys.readouterr().err
    assert "40x40 pixels" in err and "64x64" in err and "32x32" in err and err.count("\n") == 1
