"""`polarshape calibrate polarisation`: bench frames on disk → polcal.npz, and its input errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from polarshape.cli import main
from polarshape.io.images import write_image
from polarshape.io.polarimetric import read_polarimetric_calibration

RNG = np.random.default_rng(3)
LAYOUT_DEG = np.array([[90.0, 135.0], [45.0, 0.0]])  # IMX250MZR, our convention


def _frame(size: int, stokes: tuple[float, float, float], *, black: float = 64.0, scale: float = 1.0) -> np.ndarray:
    """A 12-bit raw mosaic of a uniform Stokes vector through ideal-ish analysers (ER 200:1), small noise."""
    theta = np.radians(np.tile(LAYOUT_DEG, (size // 2, size // 2)))
    d = 199.0 / 201.0
    row = 0.5 * (stokes[0] + d * (stokes[1] * np.cos(2 * theta) + stokes[2] * np.sin(2 * theta)))
    counts = black + scale * 4000.0 * row + RNG.normal(0.0, 1.0, theta.shape)
    return np.clip(np.rint(counts), 0, 4095).astype(np.uint16)


def _write(folder: Path, frames: list[np.ndarray], stem: str) -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, f in enumerate(frames):
        p = folder / f"{stem}{i:02d}.png"
        write_image(p, f)
        paths.append(str(p))
    return paths


def _bench(tmp_path: Path, n: int = 8, size: int = 16) -> tuple[list[str], list[str], list[str], list[float]]:
    ours = [k * 180.0 / n for k in range(n)]
    pol = [_frame(size, (0.8, 0.8 * math.cos(math.radians(2 * a)), 0.8 * math.sin(math.radians(2 * a)))) for a in ours]
    flat = [_frame(size, (0.8, 0.0, 0.0)) for _ in range(4)]
    dark = [_frame(size, (0.0, 0.0, 0.0)) for _ in range(4)]
    labels = [(-a) % 180 for a in ours]  # the makers' convention
    return _write(tmp_path / "pol", pol, "p"), _write(tmp_path / "flat", flat, "f"), _write(tmp_path / "dark", dark, "d"), labels


def test_writes_a_calibration_and_prints_the_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pol, flat, dark, angles = _bench(tmp_path)
    (tmp_path / "angles.txt").write_text("".join(f"{a}\n" for a in angles))
    out = tmp_path / "polcal.npz"
    argv = ["calibrate", "polarisation", "--polariser", *pol, "--angles-file", str(tmp_path / "angles.txt"),
            "--flat", *flat, "--dark", *dark, "--bit-depth", "12", "--out", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "extinction ratio median" in text and "camera.polarimetric_calibration" in text
    cal = read_polarimetric_calibration(out, expect_shape=(16, 16))
    assert cal.info["angle_error_rms_deg"] < 1.0 and 100 < cal.info["extinction_median"]
    assert abs(float(cal.black_level.mean()) - 64.0) < 0.5
    assert main(argv) == 1  # refuses to write over it
    assert main([*argv, "--overwrite"]) == 0


def test_errors_name_the_flag_and_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pol, flat, dark, angles = _bench(tmp_path, n=6)
    base = ["calibrate", "polarisation", "--bit-depth", "12", "--out", str(tmp_path / "c.npz")]
    a = [str(x) for x in angles]

    def err(*args: str) -> str:
        assert main([*base, *args]) == 2
        return capsys.readouterr().err

    assert "≥ 3 angles" in err("--polariser", *pol[:2], "--angles", *a[:2])
    assert "5 angles for 6" in err("--polariser", *pol, "--angles", *a[:5])
    assert "exactly one of --angles" in err("--polariser", *pol)
    small = tmp_path / "small.png"
    write_image(small, _frame(8, (0.8, 0.0, 0.0)))
    assert "small.png (--flat)" in err("--polariser", *pol, "--angles", *a, "--flat", str(small))
    bright = tmp_path / "bright.png"
    write_image(bright, _frame(16, (0.8, 0.8, 0.0), scale=0.3))
    msg = err("--polariser", bright.as_posix(), *pol[1:], "--angles", *a)
    assert "different exposures" in msg and "bright.png" in msg
    msg = err("--polariser", *pol, "--angles", *a, "--bit-depth", "8")
    assert "above 255" in msg and "p00.png" in msg
    assert "barely change" in err("--polariser", *(flat + flat[:2]), "--angles", *a)
    assert "file not found" in err("--polariser", *pol[:5], str(tmp_path / "nope.png"), "--angles", *a)
