"""Capture format 2: several exposures per light (exposure_us, brackets); format 1 still read and written."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from polarshape.errors import CaptureError
from polarshape.io.capture import (
    CAPTURE_FORMAT,
    CAPTURE_FORMAT_BRACKETS,
    Capture,
    load_capture,
    parse_capture_spec,
    write_capture,
)

CAMERA = {"projection": "orthographic", "bit_depth": 12}


def _light(k: int, exposures: tuple[float, ...] = (8000.0, 1000.0, 125.0)) -> dict[str, Any]:
    entry: dict[str, Any] = {"direction": [0.0, 0.6, -0.8] if k % 2 else [0.0, 0.0, -1.0],
                             "frame": f"frames/{k:03d}.png", "exposure_us": exposures[0]}
    entry["brackets"] = [{"frame": f"frames/{k:03d}_b{j}.png", "exposure_us": e} for j, e in enumerate(exposures[1:], 1)]
    return entry


def _bracketed(k: int = 2, b: int = 3, h: int = 8, w: int = 10, seed: int = 0) -> Capture:
    spec = parse_capture_spec({"format": CAPTURE_FORMAT_BRACKETS, "camera": CAMERA,
                               "lights": [_light(i, (8000.0, 1000.0, 125.0)[:b]) for i in range(k)]})
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 4096, (k, h, w)).astype(np.uint16)
    brackets = rng.integers(0, 4096, (k, b - 1, h, w)).astype(np.uint16)
    return Capture(spec=spec, frames=frames, brackets=brackets)


def test_format_2_round_trip(tmp_path: Path) -> None:
    capture = _bracketed()
    write_capture(tmp_path / "cap", capture)
    doc = yaml.safe_load((tmp_path / "cap" / "capture.yaml").read_text())
    assert doc["format"] == CAPTURE_FORMAT_BRACKETS
    assert doc["lights"][1]["brackets"][1] == {"frame": "frames/001_b2.png", "exposure_us": 125.0}
    loaded = load_capture(tmp_path / "cap")
    np.testing.assert_array_equal(loaded.frames, capture.frames)
    np.testing.assert_array_equal(loaded.brackets, capture.brackets)
    assert loaded.has_brackets and loaded.spec.bracket_size == 3
    np.testing.assert_array_equal(loaded.spec.exposures_us, [[8000, 1000, 125]] * 2)
    np.testing.assert_array_equal(loaded.bracket(1), np.concatenate([capture.frames[1:2], capture.brackets[1]]))


def test_one_frame_per_light_is_still_format_1(tmp_path: Path) -> None:
    spec = parse_capture_spec({"format": CAPTURE_FORMAT, "camera": CAMERA,
                               "lights": [{"direction": [0, 0, -1], "frame": "frames/000.png"}]})
    capture = Capture(spec=spec, frames=np.full((1, 4, 4), 100, np.uint16))
    write_capture(tmp_path / "v1", capture)
    text = (tmp_path / "v1" / "capture.yaml").read_text()
    assert "polarshape-capture/1" in text and "exposure_us" not in text and "brackets" not in text
    loaded = load_capture(tmp_path / "v1")
    assert not loaded.has_brackets and loaded.brackets is None and loaded.spec.exposures_us is None
    assert loaded.bracket(0).shape == (1, 4, 4)


@pytest.mark.parametrize("lights,fragment", [
    ([{**_light(0), "brackets": [{"frame": "frames/000_b1.png", "exposure_us": 8000.0}]}],
     "brackets[0].exposure_us 8000 is also the exposure of frame"),
    ([{**_light(0), "exposure_us": 0}], "lights[0].exposure_us: must be a positive exposure time"),
    ([{**_light(0), "brackets": [{"frame": "frames/000_b1.png", "exposure_us": -5}]}],
     "brackets[0].exposure_us: must be a positive exposure time"),
    ([{k: v for k, v in _light(0).items() if k != "exposure_us"}], "brackets need exposure_us"),
    ([{"direction": [0, 0, -1], "frame": "frames/000.png"}], "lights[0].exposure_us is required"),
    ([_light(0), _light(1, (8000.0, 1000.0))], "every light needs the same number of exposures"),
    ([{**_light(0), "brackets": [{"frame": "frames/000.png", "exposure_us": 1000.0}]}],
     "is also the frame of lights[0].frame"),
])
def test_format_2_errors_name_the_field_and_the_fix(lights: list, fragment: str) -> None:
    with pytest.raises(CaptureError) as err:
        parse_capture_spec({"format": CAPTURE_FORMAT_BRACKETS, "camera": CAMERA, "lights": lights}, "x/capture.yaml")
    assert fragment in str(err.value) and "x/capture.yaml" in str(err.value)


def test_format_1_refuses_brackets() -> None:
    with pytest.raises(CaptureError, match="need format 'polarshape-capture/2'"):
        parse_capture_spec({"format": CAPTURE_FORMAT, "camera": CAMERA, "lights": [_light(0)]})


def test_missing_bracket_frame_names_the_file_and_key(tmp_path: Path) -> None:
    write_capture(tmp_path / "cap", _bracketed())
    (tmp_path / "cap" / "frames" / "001_b2.png").unlink()
    with pytest.raises(CaptureError, match=r"001_b2\.png \(lights\[1\]\.brackets\[1\]\.frame in capture\.yaml\): "
                                           r"file not found; add the frame or fix lights\[1\]\.brackets\[1\]\.frame"):
        load_capture(tmp_path / "cap")


def test_in_memory_brackets_must_match_the_spec(tmp_path: Path) -> None:
    capture = _bracketed()
    bad = Capture(spec=capture.spec, frames=capture.frames, brackets=capture.brackets[:, :1])
    with pytest.raises(CaptureError, match=r"Capture\.brackets must be a \(2, 2, 8, 10\) uint16 array"):
        write_capture(tmp_path / "bad", bad)
    with pytest.raises(CaptureError, match="Capture.brackets is missing"):
        write_capture(tmp_path / "bad", Capture(spec=capture.spec, frames=capture.frames))


def test_the_documented_format_2_example_is_valid() -> None:
    import re

    text = (Path(__file__).resolve().parents[2] / "docs" / "capture-format.md").read_text(encoding="utf-8")
    example = next(b for b in re.findall(r"```yaml\n(.*?)```", text, flags=re.S) if CAPTURE_FORMAT_BRACKETS in b)
    spec = parse_capture_spec(yaml.safe_load(example), "docs/capture-format.md")
    assert spec.bracket_size == 3 and spec.exposures_us.shape == (2, 3)
