"""Capture sessions: bracketing, averaging, atomic per-light saving, resume after an interruption."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import torch
import yaml

from polarshape.acquisition.aravis import AravisCamera
from polarshape.acquisition.camera import CameraError, Frame
from polarshape.acquisition.fake_gige import REFERENCE_EXPOSURE_US, FakeGigECamera, synthetic_mosaic
from polarshape.acquisition.lights import RigLight, SimulatedLightRig
from polarshape.acquisition.session import average_frames, capture_session, load_session_config, run_capture_session
from polarshape.io.atomic import OutputExistsError
from polarshape.io.capture import CAPTURE_FORMAT

from session_stubs import FailingRig as _FailingRig  # noqa: E402 - the stubs beside these tests
from session_stubs import StubCamera as _StubCamera  # noqa: E402

SPECS = [RigLight(direction=(np.sin(t), 0.1, -np.cos(t)), intensity=1.0) for t in np.linspace(0.1, 0.8, 5)]


def test_average_frames_rounds_the_mean() -> None:
    a = Frame(np.array([[1, 4]], np.uint16), 12, "PolarizeMono12", 1.0, 0.0)
    b = Frame(np.array([[2, 4]], np.uint16), 12, "PolarizeMono12", 1.0, 0.0)
    np.testing.assert_array_equal(average_frames([a, b, b]), [[2, 4]])
    with pytest.raises(ValueError, match="at least one frame"):
        average_frames([])


def test_bracketing_interruption_and_resume(tmp_path: Path) -> None:
    cam = _StubCamera()
    out = tmp_path / "cap"
    rig = _FailingRig(cam, SPECS, fail_at=3)
    with pytest.raises(KeyboardInterrupt):
        run_capture_session(cam, rig, out, frames_per_light=2, exposure_bracket=[1000, 4000, 16000])
    saved = sorted(p.name for p in (out / "frames").iterdir())
    assert saved == ["000.json", "000.png", "001.json", "001.png", "002.json", "002.png", "session.json"]
    assert not (out / "capture.yaml").exists()
    before = {p: p.read_bytes() for p in (out / "frames").iterdir()}

    with pytest.raises(OutputExistsError, match="already holds frames"):
        run_capture_session(cam, SimulatedLightRig(cam, SPECS), out, resume=False)

    rig2 = _FailingRig(cam, SPECS)
    path = run_capture_session(cam, rig2, out, frames_per_light=2, exposure_bracket=[1000, 4000, 16000])
    assert rig2.switched == [3, 4]  # lights 0-2 were kept
    assert all(p.read_bytes() == data for p, data in before.items())

    doc = yaml.safe_load(path.read_text())
    assert doc["format"] == CAPTURE_FORMAT
    assert doc["camera"]["bit_depth"] == 12
    assert doc["camera"]["mosaic"]["layout"] == [[90, 45], [135, 0]]
    chosen = []
    for i, light in enumerate(doc["lights"]):
        meta = json.loads((out / "frames" / f"{i:03d}.json").read_text())
        assert meta["frames_averaged"] == 2 and meta["saturated_fraction"] < 0.001
        chosen.append(meta["exposure_us"])
        assert light["frame"] == f"frames/{i:03d}.png"
        assert light["direction"] == pytest.approx(list(SPECS[i].direction))
        image = cv2.imread(str(out / light["frame"]), cv2.IMREAD_UNCHANGED)
        assert image.dtype == np.uint16 and image.shape == (48, 64)
        assert image.max() <= 4095
    # the longest exposure with < 0.1 % saturated pixels: light 0 peaks at 3200 counts at 16000 µs,
    # light 1 would saturate 36 % of its pixels at 16000 µs
    assert chosen == [16000, 4000, 4000, 4000, 4000]
    # lights captured at shorter exposures are given proportionally lower intensities
    assert [round(light["intensity"], 6) for light in doc["lights"]] == [1.0, 0.25, 0.25, 0.25, 0.25]

    # a complete capture is returned as is
    assert run_capture_session(cam, _FailingRig(cam, SPECS, fail_at=0), out) == path


@pytest.mark.parametrize("change, field", [
    ({"specs": [RigLight(direction=(-d[0], d[1], d[2])) for d in (s.direction for s in SPECS)]}, "lights[0]"),
    ({"settings": {"roi": (0, 0, 32, 24)}}, "camera.roi"),
    ({"settings": {"pixel_format": "PolarizeMono8"}}, "camera.pixel_format"),
    ({"frames_per_light": 3}, "capture.frames_per_light"),
])
def test_resume_refuses_another_session_before_capturing(tmp_path: Path, change: dict, field: str) -> None:
    """Issue 12: a resume whose lights, ROI, pixel format or capture settings differ from the frames
    on disk is refused at the start, naming the field; nothing is captured or overwritten."""
    from polarshape.errors import CaptureError

    cam = _StubCamera()
    out = tmp_path / "cap"
    settings = {"pixel_format": "PolarizeMono12", "exposure_us": 1000.0, "roi": None}
    with pytest.raises(KeyboardInterrupt):
        run_capture_session(cam, _FailingRig(cam, SPECS, fail_at=2), out, settings=settings)
    before = {p.name: p.read_bytes() for p in (out / "frames").iterdir()}
    captured = len(cam.captured)
    specs = change.get("specs", SPECS)
    rig = _FailingRig(cam, specs)
    with pytest.raises(CaptureError, match=field.replace("[", r"\[").replace("]", r"\]")):
        run_capture_session(cam, rig, out, settings={**settings, **change.get("settings", {})},
                            frames_per_light=change.get("frames_per_light", 1))
    assert rig.switched == [] and len(cam.captured) == captured
    assert {p.name: p.read_bytes() for p in (out / "frames").iterdir()} == before
    # the same session resumes
    run_capture_session(cam, _FailingRig(cam, SPECS), out, settings=settings)
    assert (out / "capture.yaml").exists()


def test_written_capture_loads_with_load_capture(tmp_path: Path) -> None:
    module = pytest.importorskip("polarshape.io.capture", reason="polarshape.io.capture not written yet")
    cam = _StubCamera()
    run_capture_session(cam, SimulatedLightRig(cam, SPECS), tmp_path / "cap", frames_per_light=1)
    capture = module.load_capture(tmp_path / "cap")
    assert capture is not None


@pytest.mark.usefixtures("require_aravis")
def test_session_over_gige_with_interruption(tmp_path: Path) -> None:
    out = tmp_path / "gige"
    with FakeGigECamera(serial="PSSESSION", width=128, height=64) as fake, \
            AravisCamera(fake.address, trigger="software", packet_size=1400) as cam:
        cam.configure(pixel_format="PolarizeMono8")
        with pytest.raises(KeyboardInterrupt):
            run_capture_session(cam, _FailingRig(fake, SPECS, fail_at=3), out, frames_per_light=2,
                                exposure_bracket=[2500, 9000, 20000])
        rig = _FailingRig(fake, SPECS)
        path = run_capture_session(cam, rig, out, frames_per_light=2, exposure_bracket=[2500, 9000, 20000])
        assert rig.switched == [3, 4]
        for i in range(len(SPECS)):
            meta = json.loads((out / "frames" / f"{i:03d}.json").read_text())
            assert meta["exposure_us"] == 9000  # 20000 saturates half the pixels, 9000 none
            records = [fake.fill_record(fid) for fid in meta["frame_ids"]]
            assert all(r.light == i and r.exposure_us == 9000 for r in records)
            expected = np.rint(sum(r.image().astype(np.float64) for r in records) / len(records))
            image = cv2.imread(str(out / "frames" / f"{i:03d}.png"), cv2.IMREAD_UNCHANGED)
            assert image.dtype == np.uint8
            np.testing.assert_array_equal(image, expected)
            assert image.max() <= 255 * 9000 // REFERENCE_EXPOSURE_US
    doc = yaml.safe_load(path.read_text())
    assert doc["camera"]["model"] == "TRI050S-PC" and doc["camera"]["bit_depth"] == 8


@pytest.mark.usefixtures("require_aravis")
def test_capture_session_from_a_session_file(tmp_path: Path) -> None:
    session = tmp_path / "session.yaml"
    session.write_text(yaml.safe_dump({
        "camera": {"backend": "fake_gige", "address": "127.0.0.1", "trigger": "software", "packet_size": 1400,
                   "pixel_format": "PolarizeMono12p", "exposure_us": 5000, "roi": [0, 0, 64, 32],
                   "projection": "perspective", "intrinsics": {"fx": 2500.0, "fy": 2500.0, "cx": 32.0, "cy": 16.0}},
        "rig": {"type": "simulated"},
        "lights": [{"direction": [0.0, 0.0, -1.0]}, {"position": [0.1, -0.2, -0.5], "intensity": 2.0}],
        "capture": {"frames_per_light": 1},
    }))
    path = capture_session(session, tmp_path / "out")
    doc = yaml.safe_load(path.read_text())
    assert doc["camera"]["projection"] == "perspective" and doc["camera"]["intrinsics"]["fx"] == 2500.0
    assert doc["camera"]["bit_depth"] == 12
    assert doc["lights"][1] == {"position": [0.1, -0.2, -0.5], "intensity": 2.0, "frame": "frames/001.png"}
    image = cv2.imread(str(tmp_path / "out" / "frames" / "000.png"), cv2.IMREAD_UNCHANGED)
    assert image.shape == (32, 64) and image.dtype == np.uint16
    try:
        from polarshape.io.capture import load_capture
    except ImportError:
        return
    load_capture(tmp_path / "out")


def test_session_file_errors_name_the_field(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"camera": {"backend": "aravis"}, "rig": {"type": "manual"},
                                   "lights": [{"direction": [0, 0, -1]}]}))
    with pytest.raises(ValueError, match="camera.address is required"):
        load_session_config(bad)
    bad.write_text(yaml.safe_dump({"camera": {"backend": "aravis", "address": "10.0.0.2"},
                                   "rig": {"type": "serial", "port": "/dev/ttyACM0"}}))
    with pytest.raises(ValueError, match="lights: list one entry per light"):
        load_session_config(bad)
    bad.write_text("camera: [")
    with pytest.raises(ValueError, match="not valid YAML"):
        load_session_config(bad)
    bad.write_text(yaml.safe_dump({"camera": {"backend": "aravis", "address": "10.0.0.2", "projection": "perspective"},
                                   "rig": {"type": "manual"}, "lights": [{"direction": [0, 0, -1]}]}))
    with pytest.raises(ValueError, match="camera.intrinsics .* is required with projection 'perspective'"):
        load_session_config(bad)


@pytest.mark.parametrize(
    "camera,lights,fragment",
    [
        ({"intrinsics": {"fx": -1, "fy": 1, "cx": 0, "cy": 0}}, [{"direction": [0, 0, -1]}], r"intrinsics\.fx"),
        ({"intrinsics": {"fx": 1, "fy": 1, "cx": 0}}, [{"direction": [0, 0, -1]}], r"intrinsics\.cy"),
        ({"distortion": [0.1, 0.0]}, [{"direction": [0, 0, -1]}], "4, 5, 8, 12 or 14 OpenCV coefficients"),
        ({}, [{"direction": [0, 0, 1]}], r"lights\.0\.direction\s+Value error, z = 1 must be < 0"),
        ({}, [{"direction": [0, 0, -1], "position": [0, 0, -1]}], "exactly one of direction"),
    ],
)
def test_session_camera_and_lights_use_the_capture_schema(tmp_path: Path, camera, lights, fragment) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"camera": {"backend": "aravis", "address": "10.0.0.2", **camera},
                                   "rig": {"type": "manual"}, "lights": lights}))
    with pytest.raises(ValueError, match=fragment):
        load_session_config(bad)


def test_session_lights_need_not_be_unit_vectors(tmp_path: Path) -> None:
    good = tmp_path / "good.yaml"
    good.write_text(yaml.safe_dump({"camera": {"backend": "aravis", "address": "10.0.0.2"}, "rig": {"type": "manual"},
                                    "lights": [{"direction": [0.3, -0.2, -0.93], "name": "top"}]}))
    light = load_session_config(good).lights[0].to_rig_light()
    assert light.name == "top" and light.direction == pytest.approx(np.array([0.3, -0.2, -0.93]) / np.sqrt(0.9949))


def test_run_refuses_bad_lights_and_missing_intrinsics_before_capturing(tmp_path: Path) -> None:
    cam = _StubCamera()
    behind = SimulatedLightRig(cam, [RigLight(direction=(0, 0, 1))])
    with pytest.raises(ValueError, match="light 0: direction .* z >= 0"):
        run_capture_session(cam, behind, tmp_path / "a")
    with pytest.raises(ValueError, match="needs intrinsics"):
        run_capture_session(cam, SimulatedLightRig(cam, SPECS), tmp_path / "b",
                            camera_info={"projection": "perspective"})
    assert cam.captured == [] and not (tmp_path / "a").exists()


@pytest.mark.usefixtures("require_aravis")
def test_fake_camera_capture_is_accepted_by_polarshape_run(tmp_path: Path) -> None:
    """`polarshape capture` (fake GigE camera over loopback + simulated rig) → `polarshape run`."""
    from polarshape.cli import main

    session = tmp_path / "session.yaml"
    session.write_text(yaml.safe_dump({
        "camera": {"backend": "fake_gige", "address": "127.0.0.1", "trigger": "software", "packet_size": 1400,
                   "pixel_format": "PolarizeMono12p", "exposure_us": 5000, "roi": [0, 0, 64, 64],
                   "projection": "orthographic"},
        "rig": {"type": "simulated"},
        "lights": [{"direction": [0.259, 0.0, -0.966]}, {"direction": [0.0, 0.259, -0.966]},
                   {"direction": [-0.259, 0.0, -0.966]}, {"direction": [0.0, -0.259, -0.966]}],
        "capture": {"frames_per_light": 2},
    }))
    assert main(["capture", str(session), "--out", str(tmp_path / "capture")]) == 0
    (tmp_path / "run.yaml").write_text(yaml.safe_dump({
        "format": "polarshape-run/1",
        "input": {"type": "capture", "path": "capture"},
        "recovery": {"model": "lambertian"},
        "report": {"enabled": False},
        "progress": False,
    }))
    assert main(["run", str(tmp_path / "run.yaml"), "--out", str(tmp_path / "result")]) == 0
    normals = np.load(tmp_path / "result" / "normals.npy")
    assert normals.shape == (32, 32, 3)  # super-pixels of the 64 × 64 ROI
    inside = np.isfinite(normals).all(-1)
    assert inside.sum() > 0 and np.allclose(np.linalg.norm(normals[inside], axis=-1), 1.0, atol=1e-4)
    params = json.loads((tmp_path / "result" / "params.json").read_text())
    assert params["capture"]["lights"] == 4 and params["capture"]["input_type"] == "capture"
    assert (tmp_path / "result" / "mesh.ply").is_file()


# -- the colour polarisation camera (IMX250MYR / TRI050S-QC) ------------------------------------------


@pytest.mark.usefixtures("require_aravis")
def test_colour_capture_on_the_fake_tri050s_qc_records_the_bayer_pattern(tmp_path: Path) -> None:
    """`polarshape capture` with a BayerRG format: a fake TRI050S-QC, raw colour mosaics on disk, and a
    capture.yaml with camera.mosaic.bayer RGGB that demosaics to per-colour Stokes."""
    from polarshape.cli import main
    from polarshape.imaging.colour import colour_stokes_from_mosaic
    from polarshape.imaging.pixels import counts_to_float
    from polarshape.io.capture import load_capture

    session = tmp_path / "session.yaml"
    session.write_text(yaml.safe_dump({
        "camera": {"backend": "fake_gige", "address": "127.0.0.1", "trigger": "software", "packet_size": 1400,
                   "pixel_format": "BayerRG12p", "exposure_us": 5000, "roi": [0, 0, 64, 32]},
        "rig": {"type": "simulated"},
        "lights": [{"direction": [0.259, 0.0, -0.966]}, {"direction": [0.0, 0.259, -0.966]}],
        "capture": {"frames_per_light": 1},
    }))
    assert main(["capture", str(session), "--out", str(tmp_path / "capture")]) == 0
    doc = yaml.safe_load((tmp_path / "capture" / "capture.yaml").read_text())
    assert doc["camera"]["model"] == "TRI050S-QC" and doc["camera"]["bit_depth"] == 12
    assert doc["camera"]["mosaic"]["bayer"] == "RGGB"
    capture = load_capture(tmp_path / "capture")
    assert capture.spec.camera.mosaic.bayer == "RGGB" and capture.frames.shape == (2, 32, 64)
    for i in range(2):
        meta = json.loads((tmp_path / "capture" / "frames" / f"{i:03d}.json").read_text())
        assert meta["pixel_format"] == "BayerRG12p" and meta["bayer"] == "RGGB"
        # the raw mosaic the fake camera sent (its synthetic scene under light i at 5000 µs)
        expected = synthetic_mosaic(64, 32, bit_depth=12, frame_id=meta["frame_ids"][0], light=i, exposure_us=5000)
        np.testing.assert_array_equal(capture.frames[i], expected)
    stokes = colour_stokes_from_mosaic(counts_to_float(capture.frames, 12), capture.layout, "RGGB")
    assert stokes.shape == (2, 3, 3, 16, 32) and torch.isfinite(stokes).all()


def _small_colour_scene(tmp_path: Path, **camera: Any) -> Path:
    doc = yaml.safe_load(Path("configs/scenes/colour.yaml").read_text())
    doc["camera"].update(width=64, height=64, pixel_size_m=2.0e-4, **camera)
    doc["lights"] = doc["lights"][:2]
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_colour_capture_on_the_simulated_backend_records_the_bayer_pattern(tmp_path: Path) -> None:
    """A session on a simulated colour scene (configs/scenes/colour.yaml, made small) in BayerRG8: raw colour
    mosaics (the orange sphere is redder than blue) and camera.mosaic.bayer RGGB in capture.yaml."""
    from polarshape.imaging.colour import colour_stokes_from_mosaic
    from polarshape.imaging.pixels import counts_to_float
    from polarshape.io.capture import load_capture

    scene = _small_colour_scene(tmp_path)
    session = tmp_path / "session.yaml"
    session.write_text(yaml.safe_dump({
        "camera": {"backend": "simulated", "scene": scene.name, "pixel_format": "BayerRG8"},
        "rig": {"type": "simulated"},
    }))
    capture = load_capture(capture_session(session, tmp_path / "out").parent)
    assert capture.spec.camera.mosaic.bayer == "RGGB" and capture.bit_depth == 8
    assert capture.frames.shape == (2, 64, 64)
    meta = json.loads((tmp_path / "out" / "frames" / "000.json").read_text())
    assert (meta["pixel_format"], meta["bayer"]) == ("BayerRG8", "RGGB")
    stokes = colour_stokes_from_mosaic(counts_to_float(capture.frames[0], 8), capture.layout, "RGGB")  # (3, 3, H, W)
    centre = stokes[:, 0, 12:20, 12:20].mean(dim=(-1, -2))  # s0 per colour at the sphere's centre
    assert centre[0] > 2 * centre[2] > 0  # body albedo k_b = [0.8, 0.45, 0.15]: red well above blue


def test_colour_format_on_a_mono_scene_is_refused(tmp_path: Path) -> None:
    from polarshape.errors import CameraError

    scene = _small_colour_scene(tmp_path, mosaic={"layout": [[90, 45], [135, 0]], "bayer": None},
                                pixel_format="PolarizeMono12")
    session = tmp_path / "session.yaml"
    session.write_text(yaml.safe_dump({
        "camera": {"backend": "simulated", "scene": scene.name, "pixel_format": "BayerRG12"},
        "rig": {"type": "simulated"},
    }))
    with pytest.raises(CameraError, match="BayerRG12 is a colour sensor's .* camera.mosaic.bayer is None"):
        capture_session(session, tmp_path / "out")
    assert not (tmp_path / "out" / "capture.yaml").exists()


def test_frames_of_one_session_must_share_one_colour_mosaic(tmp_path: Path) -> None:
    @dataclass
    class _Colour(_StubCamera):
        def capture(self, timeout_s: float = 5.0) -> Frame:
            frame = super().capture(timeout_s)
            return Frame(image=frame.image, bit_depth=12, pixel_format="BayerRG12", exposure_us=frame.exposure_us,
                         gain_db=0.0, frame_id=frame.frame_id, bayer="RGGB")

    cam = _Colour()
    path = run_capture_session(cam, SimulatedLightRig(cam, SPECS[:2]), tmp_path / "a")
    assert yaml.safe_load(path.read_text())["camera"]["mosaic"]["bayer"] == "RGGB"
    with pytest.raises(CameraError, match="contradicts the frames' colour mosaic RGGB"):
        run_capture_session(cam, SimulatedLightRig(cam, SPECS[:2]), tmp_path / "b",
                            camera_info={"mosaic": {"layout": [[90, 45], [135, 0]], "bayer": "BGGR"}})
    # a light left from a mono run of the same folder cannot be mixed with colour ones
    mono = _StubCamera()
    with pytest.raises(KeyboardInterrupt):
        run_capture_session(mono, _FailingRig(mono, SPECS[:2], fail_at=1), tmp_path / "c")
    with pytest.raises(CameraError, match="different colour mosaics"):
        run_capture_session(cam, SimulatedLightRig(cam, SPECS[:2]), tmp_path / "c")
