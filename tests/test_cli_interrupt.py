"""A real Ctrl-C (SIGINT to the process) in ``polarshape run`` and ``polarshape capture``: one line
on stderr, no traceback, exit status 130; ``run`` leaves no result, ``capture`` keeps its frames
(the same command resumes). tests/test_faults.py covers an interruption at each stage in-process."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SCENE = yaml.safe_load((REPO / "configs" / "scenes" / "sphere.yaml").read_text())


def _scene(folder: Path, width: int) -> Path:
    scene = dict(SCENE, camera={**SCENE["camera"], "width": width, "height": width, "pixel_size_m": 12e-3 / width})
    path = folder / "scene.yaml"
    path.write_text(yaml.safe_dump(scene))
    return path


def _interrupt_when(cmd: list[str], ready: Callable[[], bool]) -> tuple[int, str]:
    # SIGINT as in a terminal's foreground job: a test run started in the background of a non-interactive
    # shell (`make test &`) inherits SIGINT ignored, and Python then never raises KeyboardInterrupt
    proc = subprocess.Popen([sys.executable, "-m", "polarshape.cli", *cmd], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while not ready() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, "the command ended before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, err


@pytest.mark.slow
def test_ctrl_c_in_run_is_one_line(tmp_path: Path) -> None:
    _scene(tmp_path, 96)
    config = tmp_path / "run.yaml"
    config.write_text(yaml.safe_dump({"input": {"type": "simulated", "scene": "scene.yaml"}, "progress": False,
                                      "recovery": {"model": "fmbrdf"}}))
    out = tmp_path / "res"
    status, err = _interrupt_when(["run", str(config), "--out", str(out)],
                                  lambda: bool(list(tmp_path.glob(".res.partial-*"))))
    assert status == 130, err
    assert err == "error: interrupted (Ctrl-C); nothing half-written was kept\n"
    assert not out.exists() and not list(tmp_path.glob(".res.*"))


@pytest.mark.slow
def test_ctrl_c_in_capture_keeps_the_frames_and_the_same_command_resumes(tmp_path: Path) -> None:
    _scene(tmp_path, 64)
    session = tmp_path / "session.yaml"
    session.write_text("camera: {backend: simulated, scene: scene.yaml}\nrig: {type: simulated}\n")
    out = tmp_path / "cap"
    cmd = ["capture", str(session), "--out", str(out)]
    status, err = _interrupt_when(cmd, lambda: (out / "frames" / "000.json").exists())
    assert status == 130, err
    assert err.count("\n") == 1 and "frames captured so far are kept" in err and "Traceback" not in err
    assert (out / "frames" / "000.png").is_file() and not (out / "capture.yaml").exists()
    done = subprocess.run([sys.executable, "-m", "polarshape.cli", *cmd], capture_output=True, text=True,
                          timeout=300, check=False)
    assert done.returncode == 0 and done.stdout.startswith("wrote "), done.stderr
