"""Tests of polarshape.errors: one base class, each kind still the builtin it replaced."""

from __future__ import annotations

import warnings

import pytest

from polarshape import errors
from polarshape.acquisition.camera import CameraError
from polarshape.acquisition.lights import LightRigError
from polarshape.config import ConfigError
from polarshape.io.atomic import OutputExistsError
from polarshape.io.capture import CaptureError
from polarshape.io.images import ImageError

KINDS = [
    (errors.ConfigError, ValueError),
    (errors.CaptureError, ValueError),
    (errors.ImageError, ValueError),
    (errors.ShapeError, ValueError),
    (errors.CameraError, RuntimeError),
    (errors.LightRigError, RuntimeError),
    (errors.OutputExistsError, FileExistsError),
    (errors.PipelineError, RuntimeError),
    (errors.DeviceError, RuntimeError),
    (errors.OutputWriteError, OSError),
    (errors.OutputPathError, NotADirectoryError),
    (errors.SelfCheckError, RuntimeError),
]


@pytest.mark.parametrize(("kind", "builtin"), KINDS)
def test_every_kind_is_a_polarshape_error_and_its_builtin(kind: type[Exception], builtin: type[Exception]) -> None:
    with pytest.raises(errors.PolarshapeError, match="the message"):
        raise kind("the message")
    with pytest.raises(builtin):
        raise kind("the message")
    assert str(kind("the message")) == "the message"


def test_all_lists_every_kind() -> None:
    assert set(errors.__all__) == {k.__name__ for k, _ in KINDS} | {"PolarshapeError"} | {
        k.__name__ for k in WARNINGS}


WARNINGS = [errors.PolarshapeWarning, errors.SuspiciousInputWarning, errors.FitResidualWarning, errors.ConventionWarning,
            errors.FrameOrderWarning, errors.BitDepthWarning, errors.ParameterBoundWarning, errors.FilledPixelsWarning,
            errors.FrozenPixelsWarning, errors.ModelEvidenceWarning, errors.ClippedLobeWarning,
            errors.InterreflectionWarning, errors.LightPlacementWarning, errors.NearFieldDepthWarning]


@pytest.mark.parametrize("kind", WARNINGS)
def test_every_warning_is_a_polarshape_warning_and_a_user_warning(kind: type[Warning]) -> None:
    with pytest.warns(errors.PolarshapeWarning, match="look"):
        warnings.warn(kind("look"), stacklevel=1)
    assert issubclass(kind, UserWarning) and not issubclass(kind, errors.PolarshapeError)


def test_old_import_paths_give_the_same_classes() -> None:
    assert (ConfigError, CaptureError, ImageError, OutputExistsError, CameraError, LightRigError) == (
        errors.ConfigError, errors.CaptureError, errors.ImageError, errors.OutputExistsError,
        errors.CameraError, errors.LightRigError,
    )
