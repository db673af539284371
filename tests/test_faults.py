"""Fault injection: what polarshape promises when things go wrong (README, "What polarshape promises").

- An interrupted run (Ctrl-C, SIGTERM, SIGKILL) at any stage leaves no result and no partial folder
  (a killed run's partial is removed by the next run to the same destination), and a previous
  result it was replacing stays intact.
- A full disk or an unwritable destination is a one-line error (exit 3) that leaves nothing behind.
- A corrupt or unusable input is a one-line error (exit 2), never a traceback, never a result.
- Inputs are never touched: every file of the capture keeps its bytes.

Each run goes through the command line in-process (``polarshape.cli.main``) on a 16×16-super-pixel
capture, so the whole module takes seconds.
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

import polarshape.io.results as results
import polarshape.pipeline as pipeline
from polarshape.cli import main


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory, render_sphere: Callable[..., Path]) -> Path:
    """A 32×32-raw-pixel sphere under 8 lights, rendered once (read-only to the tests: they copy it)."""
    return render_sphere(tmp_path_factory.mktemp("faults"), width=32, pixel_size_m=8.0e-4, lights=8, seed=1)


def _config(folder: Path, capture: Path) -> Path:
    path = folder / "run.yaml"
    path.write_text(yaml.safe_dump({
        "input": {"type": "capture", "path": str(capture)}, "progress": False,
        "recovery": {"model": "lambertian"}, "mesh": {"poisson": False}, "report": {"enabled": False},
    }))
    return path


def _snapshot(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (relative path → SHA-256 of its bytes)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _leftovers(folder: Path) -> list[str]:
    """Hidden temporary entries (``.NAME.partial-*``, ``.NAME.old-*``, ``.NAME.*.tmp*``) under ``folder``."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob(".*") if ".partial-" in p.name
                  or ".old-" in p.name or ".tmp" in p.name)


def _run(config: Path, out: Path, *extra: str) -> int:
    return main(["run", str(config), "--out", str(out), "-q", *extra])


# --- interruptions at each stage ---------------------------------------------------------------

#: A public name the pipeline calls in each stage (patched in polarshape.pipeline's namespace).
STAGE_CALLS = ("acquire", "preprocess", "recover_normals", "integrate", "build_meshes", "write_maps", "evaluate",
               "write_params")


def _interrupting(name: str, exc: BaseException) -> Callable[..., object]:
    real = getattr(pipeline, name)

    def call(*args: object, **kwargs: object) -> object:
        if name in ("write_maps", "write_params"):  # files are half-written when it strikes
            real(*args, **kwargs)
        raise exc

    return call


@pytest.mark.parametrize("stage", STAGE_CALLS)
@pytest.mark.parametrize("signal_name", ["SIGINT", "SIGTERM"])
def test_an_interruption_at_any_stage_leaves_nothing_and_keeps_the_old_result(
    capture: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
    stage: str, signal_name: str,
) -> None:
    config, out = _config(tmp_path, capture), tmp_path / "res"
    before = _snapshot(capture)
    # SIGINT arrives as KeyboardInterrupt; SIGTERM as SystemExit(143) from the command line's handler
    exc: BaseException = KeyboardInterrupt() if signal_name == "SIGINT" else SystemExit(128 + signal.SIGTERM)
    monkeypatch.setattr(pipeline, stage, _interrupting(stage, exc))
    if signal_name == "SIGINT":
        assert _run(config, out) == 130
        assert "interrupted" in capsys.readouterr().err
    else:
        with pytest.raises(SystemExit) as info:
            _run(config, out)
        assert info.value.code == 143
    assert not out.exists() and _leftovers(tmp_path) == []

    monkeypatch.undo()  # a complete result, then an interrupted --overwrite of it
    assert _run(config, out) == 0
    result = _snapshot(out)
    monkeypatch.setattr(pipeline, stage, _interrupting(stage, exc))
    with pytest.raises(SystemExit) if signal_name == "SIGTERM" else _no_raise():
        _run(config, out, "--overwrite")
    assert _snapshot(out) == result and _leftovers(tmp_path) == []
    assert _snapshot(capture) == before


class _no_raise:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> bool:
        return False


@pytest.mark.slow
def test_a_killed_run_leaves_a_partial_that_the_next_run_removes(capture: Path, tmp_path: Path) -> None:
    """SIGKILL cannot be caught: its partial folder stays until the next run to that destination."""
    config, out = _config(tmp_path, capture), tmp_path / "res"
    cmd = [sys.executable, "-m", "polarshape.cli", "run", str(config), "--out", str(out), "-q"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(".res.partial-*")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert proc.poll() is None, "the run ended before it could be killed"
    proc.kill()
    proc.wait(timeout=60)
    assert list(tmp_path.glob(".res.partial-*")) and not out.exists()
    assert _run(config, out) == 0
    assert _leftovers(tmp_path) == [] and (out / "params.json").is_file()


# --- full disk, unwritable destination ------------------------------------------------------------


@pytest.mark.parametrize("where", ["first_map", "params"])
def test_a_full_disk_is_a_one_line_error_that_leaves_nothing(
    capture: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], where: str,
) -> None:
    config, out = _config(tmp_path, capture), tmp_path / "res"

    def full(*args: object, **kwargs: object) -> None:  # (array, path) or (path, text)
        path = next(a for a in args if isinstance(a, Path))
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    if where == "first_map":
        monkeypatch.setattr(results, "write_npy", full)  # normals.npy, the first result file
    else:
        monkeypatch.setattr(results, "atomic_write_text", full)  # params.json, the last one
    assert _run(config, out) == 3
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "Traceback" not in err
    assert "no space left" in err.lower()
    assert not out.exists() and _leftovers(tmp_path) == []


def test_an_unwritable_destination_is_a_one_line_error(
    capture: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    config, out = _config(tmp_path, capture), tmp_path / "locked" / "res"
    (tmp_path / "locked").mkdir()

    def denied(*args: object, **kwargs: object) -> str:
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(kwargs.get("dir", "")))

    monkeypatch.setattr(tempfile, "mkdtemp", denied)  # what a read-only parent does (tests may run as root)
    assert _run(config, out) == 3
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "permission denied" in err.lower()
    assert os.listdir(tmp_path / "locked") == []


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_parent_is_a_one_line_error(capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config, locked = _config(tmp_path, capture), tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        assert _run(config, locked / "res") == 3
        assert "permission denied" in capsys.readouterr().err.lower()
    finally:
        locked.chmod(0o755)


def test_out_under_a_regular_file_is_an_invalid_argument(capture: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    config = _config(tmp_path, capture)
    (tmp_path / "afile").write_text("mine")
    assert _run(config, tmp_path / "afile" / "res") == 2
    err = capsys.readouterr().err
    assert "afile" in err and "not a folder" in err and "Traceback" not in err
    assert (tmp_path / "afile").read_text() == "mine"


# --- corrupt and unusable inputs ---------------------------------------------------------------------


def _frames(folder: Path) -> list[Path]:
    return sorted((folder / "frames").glob("*.png"))


def _edit_yaml(folder: Path, edit: Callable[[dict], None]) -> None:
    doc = yaml.safe_load((folder / "capture.yaml").read_text())
    edit(doc)
    (folder / "capture.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))


def _set_frames(folder: Path, value: Callable[[np.ndarray], np.ndarray]) -> None:
    for path in _frames(folder):
        cv2.imwrite(str(path), value(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)))


#: name → mutation of a copy of a valid capture; each must be refused with exit 2.
CORRUPTIONS: dict[str, Callable[[Path], None]] = {
    "truncated_frame": lambda f: _frames(f)[2].write_bytes(_frames(f)[2].read_bytes()[:100]),
    "empty_frame": lambda f: _frames(f)[0].write_bytes(b""),
    "missing_frame": lambda f: _frames(f)[3].unlink(),
    "frame_of_another_size": lambda f: cv2.imwrite(str(_frames(f)[1]), np.zeros((30, 32), np.uint16)),
    "colour_frame": lambda f: cv2.imwrite(str(_frames(f)[1]), np.zeros((32, 32, 3), np.uint8)),
    "garbage_yaml": lambda f: (f / "capture.yaml").write_bytes(b"\x00\xff{[: not yaml"),
    "yaml_not_a_mapping": lambda f: (f / "capture.yaml").write_text("- a\n- b\n"),
    "no_lights": lambda f: _edit_yaml(f, lambda d: d.pop("lights")),
    "nan_direction": lambda f: _edit_yaml(f, lambda d: d["lights"][0].update(direction=[float("nan"), 0, -1])),
    "zero_direction": lambda f: _edit_yaml(f, lambda d: d["lights"][0].update(direction=[0, 0, 0])),
    "negative_intensity": lambda f: _edit_yaml(f, lambda d: d["lights"][0].update(intensity=-1.0)),
    "bit_depth_0": lambda f: _edit_yaml(f, lambda d: d["camera"].update(bit_depth=0)),
    "layout_repeats_an_angle": lambda f: _edit_yaml(f, lambda d: d["camera"]["mosaic"].update(layout=[[0, 0], [90, 135]])),
    "mask_of_another_size": lambda f: cv2.imwrite(str(f / "mask.png"), np.full((8, 8), 255, np.uint8)),
    "duplicate_yaml_key": lambda f: (f / "capture.yaml").write_text(
        (f / "capture.yaml").read_text() + "format: polarshape-capture/1\n"),
    "all_black": lambda f: _set_frames(f, np.zeros_like),
    "all_black_without_mask": lambda f: (_set_frames(f, np.zeros_like), (f / "mask.png").unlink()),
    "all_saturated": lambda f: _set_frames(f, lambda a: np.full_like(a, 4095)),
    "constant": lambda f: _set_frames(f, lambda a: np.full_like(a, 2000)),
    "black_level_above_the_signal": lambda f: _edit_yaml(f, lambda d: d["camera"].update(black_level=4000.0)),
}


@pytest.mark.parametrize("name", sorted(CORRUPTIONS))
def test_a_corrupt_or_unusable_capture_is_refused_with_a_one_line_error(
    capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str,
) -> None:
    broken = tmp_path / "capture"
    shutil.copytree(capture, broken)
    CORRUPTIONS[name](broken)
    before = _snapshot(broken)
    status = _run(_config(tmp_path, broken), tmp_path / "res")
    err = capsys.readouterr().err
    assert status == 2, err
    assert err.startswith("error: ") and "Traceback" not in err
    assert not (tmp_path / "res").exists() and _leftovers(tmp_path) == []
    assert _snapshot(broken) == before


def test_random_damage_to_capture_yaml_never_gives_a_traceback(
    capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    """Seeded byte flips in capture.yaml: every run ends in a result (the flip was harmless) or exit 2."""
    rng = np.random.default_rng(12)
    text = (capture / "capture.yaml").read_bytes()
    statuses = []
    for trial in range(12):
        broken = tmp_path / f"capture{trial}"
        shutil.copytree(capture, broken)
        data = bytearray(text)
        for at in rng.choice(len(data), size=3, replace=False):
            data[at] = int(rng.integers(32, 127))
        (broken / "capture.yaml").write_bytes(bytes(data))
        status = _run(_config(tmp_path, broken), tmp_path / f"res{trial}")
        err = capsys.readouterr().err
        assert status in (0, 2) and "Traceback" not in err, (trial, err)
        assert status == 0 or not (tmp_path / f"res{trial}").exists()
        statuses.append(status)
    assert 2 in statuses  # the generator does damage
    assert _leftovers(tmp_path) == []


def test_a_suspicious_capture_runs_with_a_named_warning_recorded_in_params(
    capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    """A copied light entry and frame: the run goes on, prints one warning line and records it."""
    import json

    copied = tmp_path / "capture"
    shutil.copytree(capture, copied)
    shutil.copyfile(_frames(copied)[1], _frames(copied)[2])
    _edit_yaml(copied, lambda d: d["lights"][2].update(direction=d["lights"][1]["direction"]))
    assert _run(_config(tmp_path, copied), tmp_path / "res") == 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("warning: SuspiciousInputWarning: ")]
    assert any("lights 1 and 2" in line for line in lines) and any("bit-identical" in line for line in lines), err
    recorded = json.loads((tmp_path / "res" / "params.json").read_text())["warnings"]
    assert len(recorded) == len(lines) == 2 and all(r.startswith("SuspiciousInputWarning: ") for r in recorded)
