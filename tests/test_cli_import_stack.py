"""``polarshape import stack``: parser, handler, printed line, exit statuses."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from polarshape.cli import main
from polarshape.io.capture import load_capture


def _stack(folder: Path) -> Path:
    """Two lights of four 4×6 16-bit polariser images (value = 1000 + label) and a light file."""
    folder.mkdir()
    for light in ("a", "b"):
        for label in (0, 45, 90, 135):
            cv2.imwrite(str(folder / f"{light}_{label}.png"), np.full((4, 6), 1000 + label, dtype=np.uint16))
    (folder.parent / "lights.txt").write_text("0 0 1\n0.6 0 0.8\n")
    return folder


def test_import_stack_writes_a_capture(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = _stack(tmp_path / "src")
    code = main(["import", "stack", str(src), "--out", str(tmp_path / "cap"), "--lights", str(tmp_path / "lights.txt"),
                 "--light-frame", "diligent", "--angles", "polanalyser", "--bit-depth", "12"])
    assert code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"wrote {tmp_path / 'cap'} (2 lights, 6x4 pixels, 12-bit, labels polanalyser)")
    assert "preprocess.demosaic: superpixel" in out
    capture = load_capture(tmp_path / "cap")
    assert capture.frames.shape == (2, 8, 12) and capture.bit_depth == 12
    # maker / polanalyser labels on the IMX250MZR sites [[90, 45], [135, 0]]
    assert capture.frames[0, :2, :2].tolist() == [[1090, 1045], [1135, 1000]]
    assert np.allclose(capture.spec.lights[1].direction, [0.6, 0, -0.8])


def test_import_stack_exit_statuses(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = _stack(tmp_path / "src")
    argv = ["import", "stack", str(src), "--out", str(tmp_path / "cap"), "--lights", str(tmp_path / "lights.txt"),
            "--light-frame", "diligent"]
    (src / "b_90.png").unlink()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "light 'b' has no 90° image" in err and not (tmp_path / "cap").exists()
    cv2.imwrite(str(src / "b_90.png"), np.full((4, 6), 7, dtype=np.uint16))
    assert main(argv) == 0
    capsys.readouterr()
    assert main(argv) == 1  # --out exists
    assert "already exists" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # the frame is required: never guessed
        main(argv[:-2])
