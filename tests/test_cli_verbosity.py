"""``-v``/``-q`` before or after any command (counts add up), and Ctrl-C as one line for every command."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import pytest
import yaml

import polarshape.cli as cli
from polarshape.cli import INTERRUPTED_MESSAGE, build_parser, iter_commands, main, output_options

def _value(action: argparse.Action) -> list[str]:
    """Values for one argument: its first choice, else a number for a numeric option (``12``), else
    ``x.yaml``, as many as ``nargs`` wants."""
    one = str(next(iter(action.choices))) if action.choices else "12" if action.type in (int, float) else "x.yaml"
    count = action.nargs if isinstance(action.nargs, int) else 1
    return [one] * count


def _command_lines() -> dict[tuple[str, ...], list[str]]:
    """A command line each command parses (its required arguments filled in), by command path."""
    lines = {}
    for path, parser in iter_commands(build_parser()):
        if parser.get_default("handler") is None:  # the top level, calibrate, import: not commands
            continue
        argv = list(path)
        for action in parser._actions:  # noqa: SLF001 - argparse keeps the arguments there
            if not action.option_strings and action.nargs != 0:
                argv += _value(action)
            elif action.required:
                argv += [action.option_strings[0], *_value(action)]
        lines[path] = argv
    return lines


COMMANDS = _command_lines()


def test_every_command_is_found() -> None:
    assert {("run",), ("simulate",), ("demo",), ("inspect",), ("capture",), ("calibrate", "lights"),
            ("calibrate", "intrinsics"), ("import", "diligent"), ("import", "lights")} <= set(COMMANDS)


@pytest.mark.parametrize("path", sorted(COMMANDS))
@pytest.mark.parametrize(
    ("before", "after", "expected"),
    [
        ([], [], (0, False)),
        (["-v"], [], (1, False)),
        ([], ["-v"], (1, False)),
        ([], ["--verbose", "--quiet"], (1, True)),
        (["-v"], ["-v"], (2, False)),  # the counts add up
        (["-vv"], ["-v", "-q"], (3, True)),
        (["-q"], [], (0, True)),
        ([], ["-q"], (0, True)),
    ],
)
def test_verbose_and_quiet_before_or_after_every_command(path: tuple[str, ...], before: list[str], after: list[str],
                                                         expected: tuple[int, bool]) -> None:
    args = build_parser().parse_args([*before, *COMMANDS[path], *after])
    assert output_options(args) == expected


def test_verbose_between_the_levels_of_a_nested_command() -> None:
    args = build_parser().parse_args(["-v", "calibrate", "-v", "lights", "a.png", "-v"])
    assert output_options(args) == (3, False)


@pytest.mark.parametrize("argv", [["inspect", "missing.png", "-vv"], ["-v", "inspect", "missing.png", "-v"],
                                  ["-vv", "inspect", "missing.png"]])
def test_vv_anywhere_shows_debug_logs(argv: list[str], tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    argv = [str(tmp_path / a) if a.endswith(".png") else a for a in argv]
    before = logging.getLogger("polarshape").level
    assert main(argv) == 2  # the missing frame; reports_errors logs the traceback at debug level
    assert any(r.levelno == logging.DEBUG and r.name.startswith("polarshape") for r in caplog.records)
    assert "Traceback" not in capsys.readouterr().err
    assert logging.getLogger("polarshape").level == before  # restored for the next caller


def test_one_v_is_not_debug(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    assert main(["inspect", str(tmp_path / "missing.png"), "-v"]) == 2
    assert not any(r.levelno == logging.DEBUG and r.name.startswith("polarshape") for r in caplog.records)


@pytest.fixture
def run_config(tmp_path: Path, render_sphere) -> Path:  # noqa: ANN001
    capture = render_sphere(tmp_path, width=32, pixel_size_m=8.0e-4, lights=6, seed=1)
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump({  # progress: true, the default
        "input": {"type": "capture", "path": str(capture)},
        "recovery": {"model": "lambertian"}, "mesh": {"poisson": False}, "report": {"enabled": False},
    }))
    return path


@pytest.mark.parametrize("where", ["none", "after", "before"])
def test_quiet_after_run_turns_off_its_progress_bar(run_config: Path, tmp_path: Path, where: str,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["run", str(run_config), "--out", str(tmp_path / f"res-{where}")]
    argv = {"none": argv, "after": [*argv, "-q"], "before": ["-q", *argv]}[where]
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert ("polarshape run" in captured.err) == (where == "none")  # the stage bar (tqdm, stderr)
    assert "result in" in captured.out  # the one-line result, with -q too


def test_quiet_after_simulate_turns_off_its_progress_bar(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = tmp_path / "scene.yaml"
    scene.write_text("camera: {projection: orthographic, width: 16, height: 16, pixel_size_m: 1.0e-3}\n"
                     "objects: [{shape: {type: sphere, center: [0, 0, 1], radius: 0.006}, "
                     "material: {model: lambertian, k_d: 0.5}}]\nlights: [{direction: [0, 0, -1]}]\n")
    assert main(["simulate", str(scene), "--out", str(tmp_path / "a")]) == 0
    assert "lights" in capsys.readouterr().err
    assert main(["simulate", str(scene), "--out", str(tmp_path / "b"), "-q"]) == 0
    captured = capsys.readouterr()
    assert "lights" not in captured.err and captured.out.startswith("wrote ")


# --- Ctrl-C ----------------------------------------------------------------------------------------


def _interrupt_every_command(monkeypatch: pytest.MonkeyPatch) -> None:
    parser = build_parser()

    def interrupted(args: object) -> int:
        raise KeyboardInterrupt

    for _, each in iter_commands(parser):
        if each.get_default("handler") is not None:
            each.set_defaults(handler=interrupted)
    monkeypatch.setattr(cli, "build_parser", lambda: parser)


@pytest.mark.parametrize("path", sorted(COMMANDS))
def test_ctrl_c_in_every_command_is_one_line_and_130(path: tuple[str, ...], monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    _interrupt_every_command(monkeypatch)
    assert main(COMMANDS[path]) == 130
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: interrupted (Ctrl-C)") and "Traceback" not in err
    if path == ("capture",):  # a session keeps its frames on purpose: the same command resumes
        assert "frames captured so far are kept" in err
    else:
        assert err.strip() == INTERRUPTED_MESSAGE


def test_ctrl_c_while_the_parser_is_built_is_one_line(monkeypatch: pytest.MonkeyPatch,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    def interrupted() -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert main(["demo", "--out", "x"]) == 130
    assert capsys.readouterr().err.strip() == INTERRUPTED_MESSAGE
