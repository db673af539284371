"""``polarshape import arena``: through :func:`polarshape.cli.main` — a capture written with the
left shift said and recorded, a refused .raw (status 2, file and fix named), an existing --out
(status 1)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from polarshape.cli import main
from polarshape.io.capture import load_capture


def _arena_folder(folder: Path) -> tuple[Path, np.ndarray]:
    """Three 8×8 16-bit PNGs of 12-bit counts left-shifted by 4, and a light file (our frame)."""
    folder.mkdir()
    counts = np.random.default_rng(0).integers(100, 4096, size=(3, 8, 8), dtype=np.uint16)
    for k, frame in enumerate(counts):
        assert cv2.imwrite(str(folder / f"img_{k}.png"), frame << 4)
    lights = folder.parent / "lights.txt"
    lights.write_text("0 0 -1\n0 0.6 -0.8\n0.6 0 -0.8\n")
    return lights, counts


def test_import_arena_writes_a_capture_and_says_the_shift(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lights, counts = _arena_folder(tmp_path / "arena")
    out = tmp_path / "capture"
    assert main(["import", "arena", str(tmp_path / "arena"), "--out", str(out), "--lights", str(lights),
                 "--light-frame", "opencv", "--black-level", "10"]) == 0
    printed = capsys.readouterr().out
    assert "left-shifted by 4" in printed and "wrote" in printed and "12-bit" in printed
    capture = load_capture(out)
    assert capture.bit_depth == 12 and np.array_equal(capture.frames, counts)
    assert capture.spec.camera.black_level == 10 and np.allclose(capture.spec.lights[1].direction, [0, 0.6, -0.8])
    assert capture.ground_truth["source"]["left_shift"] == 4

    assert main(["import", "arena", str(tmp_path / "arena"), "--out", str(out), "--lights", str(lights),
                 "--light-frame", "opencv"]) == 1
    assert "already exists" in capsys.readouterr().err


def test_import_arena_raw_without_size_is_status_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "f.raw").write_bytes(bytes(96))
    (tmp_path / "l.txt").write_text("0 0 -1\n")
    assert main(["import", "arena", str(tmp_path / "f.raw"), "--out", str(tmp_path / "c"), "--lights",
                 str(tmp_path / "l.txt"), "--light-frame", "opencv", "--pixel-format", "PolarizeMono12p"]) == 2
    err = capsys.readouterr().err
    assert "f.raw" in err and "missing --width, --height" in err and not (tmp_path / "c").exists()
