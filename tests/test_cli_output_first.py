"""An output that may not be written is refused before any work: before torch is imported (``run``
with ``--out``), before a stage (``run_pipeline``), before the scene is read (``simulate``), before the
camera is opened (``capture``), before the source is read (``import diligent``) — with the message and
exit status the refusal has always had (exit 1)."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml

import polarshape.acquisition.simulated as simulated
import polarshape.pipeline as pipeline
from polarshape.cli import main
from polarshape.config import load_run_config
from polarshape.errors import OutputExistsError
from polarshape.pipeline import run_pipeline


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory, render_sphere: Callable[..., Path]) -> Path:
    return render_sphere(tmp_path_factory.mktemp("first"), width=16, pixel_size_m=8.0e-4, lights=4, seed=1)


@pytest.fixture
def config(tmp_path: Path, capture: Path) -> Path:
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump({"input": {"type": "capture", "path": str(capture)}, "progress": False,
                                    "recovery": {"model": "lambertian"}, "report": {"enabled": False}}))
    return path


def test_run_refuses_an_existing_out_before_torch_is_imported(config: Path, tmp_path: Path) -> None:
    """The old command read the configuration (torch, seconds) and imported the pipeline first."""
    out = tmp_path / "exists"
    out.mkdir()
    code = ("import sys\nfrom polarshape.cli import main\n"
            f"status = main(['run', {str(config)!r}, '--out', {str(out)!r}])\n"
            "print(status, 'torch' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert done.stdout.split() == ["1", "False"], done.stderr
    assert done.stderr == (f"error: {out} already exists; refusing to overwrite it (pass overwrite=True / "
                           "--overwrite, or choose another output path)\n")
    assert os_listdir(out) == []


def os_listdir(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_the_early_refusal_says_what_the_pipeline_says(config: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "exists"
    out.mkdir()
    with pytest.raises(OutputExistsError) as info:
        run_pipeline(load_run_config(config), out)
    assert main(["run", str(config), "--out", str(out)]) == 1
    assert capsys.readouterr().err == f"error: {info.value}\n"


@pytest.mark.parametrize("where", ["capture", "frames", "config_folder"])
def test_an_out_that_is_an_input_keeps_the_message_naming_the_input(where: str, config: Path, capture: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = {"capture": capture, "frames": capture / "frames", "config_folder": config.parent}[where]
    assert main(["run", str(config), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "refusing to write there" in err and "input" in err, err


def test_run_pipeline_refuses_before_the_first_stage(config: Path, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    def acquire(*args: object, **kwargs: object) -> None:
        raise AssertionError("the capture was acquired before the output was refused")

    monkeypatch.setattr(pipeline, "acquire", acquire)
    (tmp_path / "exists").mkdir()
    with pytest.raises(OutputExistsError, match="already exists"):
        run_pipeline(load_run_config(config), tmp_path / "exists")
    config_without_out = load_run_config(config).model_copy(update={"output": str(tmp_path / "exists")})
    with pytest.raises(OutputExistsError, match="already exists"):
        run_pipeline(config_without_out)  # the config's output: too


def test_simulate_refuses_before_reading_the_scene(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "exists").mkdir()
    assert main(["simulate", str(tmp_path / "no_such_scene.yaml"), "--out", str(tmp_path / "exists")]) == 1
    assert "already exists" in capsys.readouterr().err


def test_import_diligent_refuses_before_reading_the_source(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "src").mkdir()  # no images, no light_directions.txt: reading it would be exit 2
    (tmp_path / "exists").mkdir()
    assert main(["import", "diligent", str(tmp_path / "src"), "--out", str(tmp_path / "exists")]) == 1
    assert "already exists" in capsys.readouterr().err


SESSION = """camera: {backend: simulated, scene: scene.yaml}
rig: {type: simulated}
"""
SCENE = """camera: {projection: orthographic, width: 16, height: 16, pixel_size_m: 1.0e-3}
objects: [{shape: {type: sphere, center: [0, 0, 1], radius: 0.006}, material: {model: lambertian, k_d: 0.5}}]
lights: [{direction: [0, 0, -1]}, {zenith_deg: 30, azimuth_deg: 0}]
"""


@pytest.mark.parametrize("existing", ["frames/000.png", "capture.yaml"])
def test_capture_without_resume_refuses_before_the_camera_opens(existing: str, tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "session.yaml").write_text(SESSION)
    (tmp_path / "scene.yaml").write_text(SCENE)
    out = tmp_path / "cap"
    (out / existing).parent.mkdir(parents=True, exist_ok=True)
    (out / existing).write_text("mine")

    class NoCamera:
        def __init__(self, *args: object, **kwargs: object) -> None:
            raise AssertionError("the camera was opened before the output was refused")

    monkeypatch.setattr(simulated, "SimulatedCamera", NoCamera)
    assert main(["capture", str(tmp_path / "session.yaml"), "--out", str(out), "--no-resume"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and ("already holds frames" in err or "already exists" in err), err
    assert (out / existing).read_text() == "mine"


def test_capture_resumes_and_completes_as_before(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The early check leaves resuming alone: a second run of a complete session captures nothing."""
    (tmp_path / "session.yaml").write_text(SESSION)
    (tmp_path / "scene.yaml").write_text(SCENE)
    out = tmp_path / "cap"
    assert main(["capture", str(tmp_path / "session.yaml"), "--out", str(out)]) == 0
    assert capsys.readouterr().out.startswith("wrote ")
    assert main(["capture", str(tmp_path / "session.yaml"), "--out", str(out)]) == 0
    assert "already complete" in capsys.readouterr().out
