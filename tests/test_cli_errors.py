"""Tests of polarshape.cli.errors: the one map from errors to exit statuses, the table in --help, and
the errors a user meets before any work (no CUDA, an unusable output path, a full disk)."""

from __future__ import annotations

import errno
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from polarshape.cli import main
from polarshape.cli.errors import EXIT_STATUS_HELP, exit_status, reports_errors
from polarshape.errors import (
    CameraError,
    CaptureError,
    ConfigError,
    DeviceError,
    ImageError,
    LightRigError,
    OutputExistsError,
    OutputPathError,
    OutputWriteError,
    PipelineError,
    ShapeError,
)
from polarshape.io.images import write_image


@pytest.mark.parametrize(
    ("exc", "status"),
    [
        (OutputExistsError("x"), 1),
        (PipelineError("x"), 3),
        (ConfigError("x"), 2),
        (CaptureError("x"), 2),
        (ImageError("x"), 2),
        (ShapeError("x"), 2),
        (CameraError("x"), 2),
        (LightRigError("x"), 2),
        (ValueError("x"), 2),
        (FileNotFoundError("x"), 2),
        (FileExistsError("x"), 2),  # only polarshape's OutputExistsError means "refused to overwrite"
        (TypeError("x"), None),
        (RuntimeError("x"), None),
    ],
)
def test_exit_status_by_kind(exc: Exception, status: int | None) -> None:
    assert exit_status(exc) == status


def test_builtin_status_applies_to_builtin_errors_only() -> None:
    assert exit_status(ValueError("x"), builtin_status=3) == 3
    assert exit_status(OSError("x"), builtin_status=3) == 3
    assert exit_status(ConfigError("x"), builtin_status=3) == 2


def test_decorated_handler_prints_the_message_and_returns_the_status(capsys: pytest.CaptureFixture[str]) -> None:
    @reports_errors()
    def handler(exc: Exception | None) -> int:
        if exc is not None:
            raise exc
        return 0

    assert handler(None) == 0
    assert handler(ConfigError("input.path: not found")) == 2
    assert capsys.readouterr().err == "error: input.path: not found\n"
    assert handler(OutputExistsError("out exists")) == 1
    assert capsys.readouterr().err == "error: out exists\n"
    with pytest.raises(TypeError):  # a programming error keeps its traceback
        handler(TypeError("bug"))
    with pytest.raises(KeyboardInterrupt):
        handler(KeyboardInterrupt())
    assert handler.__name__ == "handler"


def test_ctrl_c_is_a_message_and_exit_130(monkeypatch, capsys) -> None:
    """Ctrl-C in a command: exit status 130 and one line on stderr, no traceback."""
    import polarshape.cli as cli

    def interrupted(args):  # noqa: ANN001, ANN202
        raise KeyboardInterrupt

    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    parser.set_defaults(handler=interrupted)
    for action in parser._subparsers._group_actions:  # noqa: SLF001 - argparse's own structure
        for sub in action.choices.values():
            sub.set_defaults(handler=interrupted)
    assert cli.main(["demo", "--out", "x"]) == 130
    err = capsys.readouterr().err
    assert "interrupted" in err and "Traceback" not in err


# --- the exit-status table in --help ---------------------------------------------------------------


@pytest.mark.parametrize("argv", [[], ["run"], ["simulate"], ["inspect"], ["calibrate"], ["calibrate", "lights"]])
def test_help_ends_with_the_exit_status_table(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main([*argv, "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    table = out[out.index("exit status:"):]
    rows = [line.split()[0] for line in table.splitlines()[1:] if line.strip()]
    assert rows == ["0", "1", "2", "3", "4", "130", "143"]
    assert "  3    cannot run: a stage failed, the disk is full or not writable, no CUDA" in table
    assert EXIT_STATUS_HELP in out


def test_the_module_docstring_and_the_table_agree() -> None:
    import polarshape.cli.errors as errors_module

    for status in ("0", "1", "2", "3", "4", "130", "143"):
        assert f"* {status} —" in errors_module.__doc__ and f"  {status} " in EXIT_STATUS_HELP
    assert exit_status(DeviceError("x")) == 3 and exit_status(OutputWriteError("x")) == 3
    assert exit_status(OutputPathError("x")) == 2
    assert exit_status(OSError(errno.ENOSPC, "No space left on device")) == 3  # even a builtin one


# --- devices -------------------------------------------------------------------------------------------


TINY_SCENE = """camera: {projection: orthographic, width: 16, height: 16, pixel_size_m: 1.0e-3}
objects:
  - shape: {type: sphere, center: [0, 0, 1], radius: 0.006}
    material: {model: lambertian, k_d: 0.5}
lights: [{direction: [0, 0, -1]}, {zenith_deg: 30, azimuth_deg: 0}, {zenith_deg: 30, azimuth_deg: 120}]
"""


@pytest.fixture
def tiny_scene(tmp_path: Path) -> Path:
    path = tmp_path / "scene.yaml"
    path.write_text(TINY_SCENE)
    return path


@pytest.fixture
def no_cuda(monkeypatch: pytest.MonkeyPatch) -> None:
    """A CPU-only torch, whatever this machine has."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.version, "cuda", None)


def _one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    return err


@pytest.mark.usefixtures("no_cuda")
def test_simulate_on_cuda_without_cuda_cannot_run(tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", str(tiny_scene), "--out", str(tmp_path / "cap"), "--device", "cuda"]) == 3
    err = _one_line_error(capsys)
    assert "--device 'cuda' requested but torch has no CUDA" in err and "use --device cpu (or auto)" in err
    assert not (tmp_path / "cap").exists()


def test_simulate_on_an_unknown_device_is_invalid(tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", str(tiny_scene), "--out", str(tmp_path / "cap"), "--device", "gpu"]) == 2
    assert "--device 'gpu' is not a device" in _one_line_error(capsys)


@pytest.mark.usefixtures("no_cuda")
def test_run_on_cuda_without_cuda_cannot_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "cap").mkdir()
    config = tmp_path / "run.yaml"
    config.write_text("input: {type: capture, path: cap}\ndevice: cuda\nprogress: false\n")
    assert main(["run", str(config), "--out", str(tmp_path / "res")]) == 3
    assert "device 'cuda' requested but torch has no CUDA" in _one_line_error(capsys)
    config.write_text("input: {type: capture, path: cap}\nprogress: false\n")
    assert main(["run", str(config), "--out", str(tmp_path / "res"), "--device", "cuda"]) == 3
    assert "use --device cpu (or auto)" in _one_line_error(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "run.yaml"]


def test_a_session_on_a_device_goes_through_the_same_check(tiny_scene: Path) -> None:
    from polarshape.acquisition.simulated import SimulatedCamera

    with pytest.raises(ConfigError, match="device 'gpu' is not a device"):
        SimulatedCamera(tiny_scene, device="gpu")


# --- outputs: a file in the way, no permission, a full disk ---------------------------------------


def _left_behind(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_out_through_a_file_says_it_is_a_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "cap").mkdir()
    (tmp_path / "afile").write_text("")
    config = tmp_path / "run.yaml"
    config.write_text("input: {type: capture, path: cap}\nprogress: false\n")
    assert main(["run", str(config), "--out", str(tmp_path / "afile" / "x")]) == 2
    err = _one_line_error(capsys)
    assert f"{tmp_path / 'afile'} is a file, not a folder" in err and "Errno" not in err


def test_simulate_into_a_folder_it_may_not_create(tiny_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise PermissionError(errno.EACCES, "Permission denied", str(args[0] if args else kwargs.get("dir")))

    monkeypatch.setattr(os, "mkdir", refuse)  # as in a read-only parent (chmod does not stop root)
    assert main(["simulate", str(tiny_scene), "--out", str(tmp_path / "ro" / "cap"), "-q"]) == 3
    assert f"cannot create {tmp_path / 'ro'}: permission denied" in _one_line_error(capsys)
    monkeypatch.undo()
    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    assert main(["simulate", str(tiny_scene), "--out", str(tmp_path / "cap"), "-q"]) == 3
    assert f"cannot create {tmp_path / 'cap'}: permission denied" in _one_line_error(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


def test_simulate_onto_a_full_disk(tiny_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    def full(self: Path, data: bytes) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", full)
    assert main(["simulate", str(tiny_scene), "--out", str(tmp_path / "cap"), "-q"]) == 3
    err = _one_line_error(capsys)
    assert f"no space left on device while writing {tmp_path / 'cap'} (" in err
    assert "free space or choose another --out" in err
    assert not (tmp_path / "cap").exists() and _left_behind(tmp_path) == []  # no .cap.partial-*


# --- inspect ------------------------------------------------------------------------------------------


def test_inspect_with_a_layout_that_is_no_permutation(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    frame = tmp_path / "frame.png"
    write_image(frame, np.full((8, 8), 100, dtype=np.uint16))
    assert main(["inspect", str(frame), "--layout", "0", "0", "0", "0"]) == 2
    err = _one_line_error(capsys)
    assert "--layout 0 0 0 0: must hold each of 0, 45, 90, 135 once" in err
