"""The errors polarshape raises on purpose, under one base class.

Every kind also subclasses the builtin it replaced (``ValueError``, ``RuntimeError`` or
``FileExistsError``), so ``except ValueError`` in user code keeps catching a :class:`ConfigError`.
The command line maps :class:`PolarshapeError` to an exit status and prints its message, never a
traceback (see :func:`polarshape.cli.reports_errors`).

Data flow: this module imports nothing from polarshape; every stage may import it.
"""

from __future__ import annotations

__all__ = [
    "CameraError",
    "CaptureError",
    "ConfigError",
    "ImageError",
    "LightRigError",
    "OutputExistsError",
    "PipelineError",
    "PolarshapeError",
    "ShapeError",
]


class PolarshapeError(Exception):
    """Every error a user can cause (a bad file, configuration, argument or device state).

    The message names the cause and the fix. The command line maps it to exit status 2 (1 for
    :class:`OutputExistsError`, 3 for :class:`PipelineError`) and prints ``error: <message>``,
    never a traceback.
    """


class ConfigError(PolarshapeError, ValueError):
    """An invalid run configuration; the message names every bad key path and the fix."""


class CaptureError(PolarshapeError, ValueError):
    """A capture folder or :class:`Capture` is invalid; the message names the file, the field and the fix."""


class ImageError(PolarshapeError, ValueError):
    """An image file is missing, unreadable or not a single-channel 8/16-bit image."""


class ShapeError(PolarshapeError, ValueError):
    """An array or tensor argument has the wrong shape; the message names the argument, the
    expected shape and the shape received (raised by :func:`polarshape.checks.check_shape`)."""


class CameraError(PolarshapeError, RuntimeError):
    """A camera could not do what was asked; the message names the cause and the fix."""


class LightRigError(PolarshapeError, RuntimeError):
    """A light rig could not do what was asked; the message names the cause and the fix."""


class OutputExistsError(PolarshapeError, FileExistsError):
    """The destination exists and overwriting was not allowed."""


class PipelineError(PolarshapeError, RuntimeError):
    """A stage cannot run with this capture and configuration; the message names the key to change."""
