"""Tests of polarshape.cli.errors: the one map from errors to exit statuses."""

from __future__ import annotations

import pytest

from polarshape.cli.errors import exit_status, reports_errors
from polarshape.errors import (
    CameraError,
    CaptureError,
    ConfigError,
    ImageError,
    LightRigError,
    OutputExistsError,
    PipelineError,
    ShapeError,
)


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
