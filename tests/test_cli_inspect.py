"""`polarshape inspect`: the rotating-polariser check of the README, on synthetic frames."""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from polarshape.cli import build_parser, main
from polarshape.imaging.mosaic import MAKER_ANGLES, MosaicLayout, mosaic_from_stokes
from polarshape.imaging.pixels import float_to_counts
from polarshape.io.images import write_image


def _polarised_frame(path: Path, phi_deg: float, dolp: float = 0.8) -> None:
    phi = math.radians(phi_deg)
    s = torch.tensor([0.5, 0.5 * dolp * math.cos(2 * phi), 0.5 * dolp * math.sin(2 * phi)], dtype=torch.float64)
    stokes = s[:, None, None].expand(3, 32, 48)
    mosaic = mosaic_from_stokes(stokes, MosaicLayout.imx250mzr())
    write_image(path, float_to_counts(mosaic, 12))


@pytest.mark.parametrize("phi", [0.0, 30.0, 60.0, -45.0, 89.0])
def test_inspect_reports_the_polariser_angle(tmp_path: Path, capsys: pytest.CaptureFixture[str], phi: float) -> None:
    f = tmp_path / "frame.png"
    _polarised_frame(f, phi)
    assert main(["inspect", str(f), "--bit-depth", "12"]) == 0
    out = capsys.readouterr().out
    aolp = float(re.search(r"AoLP ([+-][0-9.]+) deg", out).group(1))
    dolp = float(re.search(r"DoLP ([0-9.]+)", out).group(1))
    diff = (aolp - phi + 90.0) % 180.0 - 90.0
    assert abs(diff) < 0.2 and dolp == pytest.approx(0.8, abs=0.01)
    # the wrong angle direction reads the mirrored angle
    assert main(["inspect", str(f), "--angles", "clockwise_on_screen"]) == 0
    aolp_cw = float(re.search(r"AoLP ([+-][0-9.]+) deg", capsys.readouterr().out).group(1))
    if abs(((phi + 90) % 180) - 90) not in (0.0, 90.0) and abs(phi) != 45.0:
        assert abs(((aolp_cw + phi + 90.0) % 180.0) - 90.0) < 0.2


def test_inspect_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["inspect", str(tmp_path / "missing.png")]) == 2
    assert "missing.png" in capsys.readouterr().err
    rgb = tmp_path / "rgb.png"
    cv2.imwrite(str(rgb), np.zeros((8, 8, 3), dtype=np.uint8))
    assert main(["inspect", str(rgb), "--bit-depth", "8"]) == 2
    assert "single-channel" in capsys.readouterr().err


@pytest.mark.parametrize("angles", MAKER_ANGLES)
def test_inspect_offers_every_angle_convention(angles: str) -> None:
    args = build_parser().parse_args(["inspect", "frame.png", "--angles", angles])
    assert args.angles == angles
