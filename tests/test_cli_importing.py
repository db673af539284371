"""``polarshape import diligent`` and ``polarshape import lights``: parsers, handlers, exit statuses."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pytest

from polarshape.cli.importing import add_parsers
from polarshape.io.capture import Capture, CaptureSpec, load_capture, write_capture


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="polarshape")
    add_parsers(parser.add_subparsers(dest="command", required=True))
    return parser


def _run(*argv: str) -> int:
    args = _parser().parse_args(list(argv))
    return args.handler(args)


def _diligent(folder: Path) -> Path:
    """A 4×4-pixel DiLiGenT-style folder with 3 RGB images."""
    folder.mkdir()
    names = []
    for k in range(3):
        names.append(f"{k + 1:03d}.png")
        cv2.imwrite(str(folder / names[-1]), np.full((4, 4, 3), 1000 * (k + 1), dtype=np.uint16))
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    (folder / "light_directions.txt").write_text("0 0 1\n0 0.6 0.8\n0.6 0 0.8\n")
    (folder / "light_intensities.txt").write_text("1 1 1\n2 2 2\n1 1 1\n")
    cv2.imwrite(str(folder / "mask.png"), np.full((4, 4), 255, dtype=np.uint8))
    return folder


def _capture(path: Path, k: int = 3) -> Path:
    spec = CaptureSpec.model_validate({
        "format": "polarshape-capture/1", "camera": {"projection": "orthographic", "bit_depth": 12},
        "lights": [{"direction": [0, 0, -1], "frame": f"frames/{i:03d}.png"} for i in range(k)],
    })
    return write_capture(path, Capture(spec=spec, frames=np.full((k, 4, 4), 7, dtype=np.uint16)))


def test_import_diligent_writes_a_capture(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = _diligent(tmp_path / "src")
    assert _run("import", "diligent", str(src), "--out", str(tmp_path / "cap")) == 0
    assert "wrote" in capsys.readouterr().out
    capture = load_capture(tmp_path / "cap")
    assert capture.frames.shape == (3, 8, 8) and capture.mask.all()
    assert np.allclose(capture.spec.lights[1].direction, [0, -0.6, -0.8]) and capture.spec.lights[1].intensity == 2.0


def test_import_diligent_options(tmp_path: Path) -> None:
    src = _diligent(tmp_path / "src")
    (src / "light_directions.txt").write_text("0 0 -1\n0 0.6 -0.8\n0.6 0 -0.8\n")  # already our frame
    assert _run("import", "diligent", str(src), "--out", str(tmp_path / "cap"), "--light-frame", "opencv",
                "--rgb-weights", "0", "1", "0") == 0
    capture = load_capture(tmp_path / "cap")
    assert np.allclose(capture.spec.lights[1].direction, [0, 0.6, -0.8]) and capture.frames[2, 0, 0] == 3000


def test_import_diligent_refuses_an_existing_out(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = _diligent(tmp_path / "src")
    assert _run("import", "diligent", str(src), "--out", str(tmp_path / "cap")) == 0
    assert _run("import", "diligent", str(src), "--out", str(tmp_path / "cap")) == 1
    assert "already exists" in capsys.readouterr().err
    assert _run("import", "diligent", str(src), "--out", str(tmp_path / "cap"), "--overwrite") == 0
    assert _run("import", "diligent", str(src), "--out", str(src), "--overwrite") == 1  # never the source
    assert (src / "001.png").is_file()


def test_import_diligent_invalid_input_is_status_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = _diligent(tmp_path / "src")
    (src / "light_directions.txt").write_text("0 0 1\n0 zero 1\n0 0 1\n")
    assert _run("import", "diligent", str(src), "--out", str(tmp_path / "cap")) == 2
    assert "light_directions.txt:2" in capsys.readouterr().err and not (tmp_path / "cap").exists()


def test_import_lights_into_a_capture(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cap = _capture(tmp_path / "cap")
    lp = tmp_path / "dirs.lp"
    lp.write_text("3\n000.jpg 0 0 1\n001.jpg 0 0.6 0.8\n002.jpg 0.6 0 0.8\n")
    assert _run("import", "lights", str(lp), "--frame", "diligent", "--capture", str(cap)) == 0
    assert "wrote 3 light directions" in capsys.readouterr().out
    assert np.allclose(load_capture(cap).spec.lights[2].direction, [0.6, 0, -0.8])
    txt = tmp_path / "lights.txt"
    txt.write_text("0 0 -1\n0 0.6 -0.8\n0.6 0 -0.8\n")
    assert _run("import", "lights", str(txt), "--light-frame", "opencv", "--capture", str(cap / "capture.yaml")) == 0
    assert np.allclose(load_capture(cap).spec.lights[1].direction, [0, 0.6, -0.8])


def test_import_lights_refuses_a_count_mismatch(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cap = _capture(tmp_path / "cap")
    before = (cap / "capture.yaml").read_text()
    txt = tmp_path / "lights.txt"
    txt.write_text("0 0 1\n0 0.6 0.8\n")
    assert _run("import", "lights", str(txt), "--frame", "diligent", "--capture", str(cap)) == 2
    assert "2 light(s) for the 3 frame(s)" in capsys.readouterr().err
    assert (cap / "capture.yaml").read_text() == before


def test_import_lights_needs_the_frame(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        _parser().parse_args(["import", "lights", "l.txt", "--capture", "cap"])
    assert exit_info.value.code == 2 and "--frame" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        _parser().parse_args(["import", "lights", "l.txt", "--frame", "opengl", "--capture", "cap"])
