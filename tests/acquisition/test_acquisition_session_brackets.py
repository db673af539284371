"""Capture sessions with exposure brackets (capture.exposures_us): every exposure under every light,
format 2, resumable; on the simulated camera and over GigE (fake camera)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from polarshape.acquisition.lights import RigLight
from polarshape.acquisition.session import capture_session, load_session_config, run_capture_session
from polarshape.errors import CaptureError
from polarshape.io.capture import CAPTURE_FORMAT_BRACKETS, load_capture
from polarshape.recover.preprocess import preprocess_capture

from session_stubs import FailingRig as _FailingRig  # noqa: E402 - the stubs beside these tests
from session_stubs import StubCamera as _StubCamera  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
SPECS = [RigLight(direction=(np.sin(t), 0.1, -np.cos(t)), intensity=1.0) for t in np.linspace(0.1, 0.8, 4)]
EXPOSURES = [8000.0, 1000.0, 125.0]


def test_session_takes_every_exposure_and_resumes(tmp_path: Path) -> None:
    cam = _StubCamera()
    out = tmp_path / "cap"
    with pytest.raises(KeyboardInterrupt):
        run_capture_session(cam, _FailingRig(cam, SPECS, fail_at=2), out, frames_per_light=2, exposures_us=EXPOSURES)
    assert {p.name for p in (out / "frames").glob("001*")} == {"001.png", "001_b1.png", "001_b2.png", "001.json"}
    (out / "frames" / "001_b2.png").unlink()  # a bracket lost: light 1 is not done
    with pytest.raises(CaptureError, match="capture.exposures_us"):  # another bracket is another session
        run_capture_session(cam, _FailingRig(cam, SPECS), out, frames_per_light=2, exposures_us=[8000.0, 1000.0])
    rig = _FailingRig(cam, SPECS)
    path = run_capture_session(cam, rig, out, frames_per_light=2, exposures_us=EXPOSURES)
    assert rig.switched == [1, 2, 3]
    # per light: 2 frames at each bracket, then 2 at the reference (the camera ends at the reference)
    assert cam.captured[-6:] == [(3, 1000.0)] * 2 + [(3, 125.0)] * 2 + [(3, 8000.0)] * 2
    doc = yaml.safe_load(path.read_text())
    assert doc["format"] == CAPTURE_FORMAT_BRACKETS
    assert doc["lights"][3]["exposure_us"] == 8000.0 and doc["lights"][3]["intensity"] == 1.0
    assert doc["lights"][3]["brackets"] == [{"frame": "frames/003_b1.png", "exposure_us": 1000.0},
                                           {"frame": "frames/003_b2.png", "exposure_us": 125.0}]
    capture = load_capture(out)
    assert capture.brackets.shape == (4, 2, 48, 64)
    assert int(capture.frames[3].max()) == 4095 and int(capture.brackets[3, 1].max()) < 4095
    meta = json.loads((out / "frames" / "003.json").read_text())
    assert [b["exposure_us"] for b in meta["brackets"]] == [1000.0, 125.0]


def test_session_file_exposures_us_errors(tmp_path: Path) -> None:
    base = {"camera": {"backend": "simulated", "scene": "s.yaml"}, "rig": {"type": "simulated"}}
    for capture, fragment in (({"exposures_us": [1000, 1000]}, "repeats an exposure time"),
                              ({"exposures_us": [1000, -5]}, "positive exposure times"),
                              ({"exposures_us": [1000, 100], "exposure_bracket": [1000]}, "exclude each other")):
        path = tmp_path / "s.yaml"
        path.write_text(yaml.safe_dump({**base, "capture": capture}))
        with pytest.raises(ValueError, match=fragment):
            load_session_config(path)


def _scene_file(tmp_path: Path) -> Path:
    d = yaml.safe_load((REPO / "configs/scenes/sphere.yaml").read_text())
    d["camera"].update(width=48, height=48, pixel_size_m=6e-4, exposure_us=40000)
    d["objects"][0]["material"].update(alpha=0.03, k_b=0.135)
    d["lights"] = d["lights"][:4]
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def test_session_brackets_on_the_simulated_camera(tmp_path: Path) -> None:
    _scene_file(tmp_path)
    session = tmp_path / "session.yaml"
    session.write_text(yaml.safe_dump({
        "camera": {"backend": "simulated", "scene": "scene.yaml"}, "rig": {"type": "simulated"},
        "capture": {"exposures_us": [40000.0, 5000.0, 625.0]}}))
    capture = load_capture(capture_session(session, tmp_path / "out"))
    assert capture.spec.bracket_size == 3
    inputs = preprocess_capture(capture)
    single = preprocess_capture(load_capture(capture_session(  # the same session without brackets
        _without_brackets(session), tmp_path / "single")))
    assert int(single.saturated[:, single.mask].sum()) > 0 and int(inputs.saturated[:, inputs.mask].sum()) == 0


def _without_brackets(session: Path) -> Path:
    doc = yaml.safe_load(session.read_text())
    doc["capture"] = {}
    doc["camera"]["exposure_us"] = 40000.0
    path = session.with_name("single.yaml")
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.usefixtures("require_aravis")
def test_session_brackets_over_gige(tmp_path: Path) -> None:
    session = tmp_path / "session.yaml"
    session.write_text(yaml.safe_dump({
        "camera": {"backend": "fake_gige", "address": "127.0.0.1", "trigger": "software", "packet_size": 1400,
                   "pixel_format": "PolarizeMono12p", "exposure_us": 5000, "roi": [0, 0, 64, 32]},
        "rig": {"type": "simulated"},
        "lights": [{"direction": [0.0, 0.0, -1.0]}, {"direction": [0.3, 0.0, -0.954]}],
        "capture": {"exposures_us": [20000.0, 2500.0]},
    }))
    capture = load_capture(capture_session(session, tmp_path / "out"))
    np.testing.assert_array_equal(capture.spec.exposures_us, [[20000.0, 2500.0]] * 2)
    assert capture.brackets.shape == (2, 1, 32, 64)
    assert int(capture.brackets.max()) < int(capture.frames.max())
