"""The errors polarshape raises on purpose, under one base class.

Every kind also subclasses the builtin it replaced (``ValueError``, ``RuntimeError`` or
``FileExistsError``), so ``except ValueError`` in user code keeps catching a :class:`ConfigError`.
The command line maps :class:`PolarshapeError` to an exit status and prints its message, never a
traceback (see :func:`polarshape.cli.reports_errors`).

Data flow: this module imports nothing from polarshape; every stage may import it.
"""

from __future__ import annotations

__all__ = [
    "BitDepthWarning",
    "CameraError",
    "CaptureError",
    "ClippedLobeWarning",
    "ConfigError",
    "ConventionWarning",
    "DeviceError",
    "FilledPixelsWarning",
    "FitResidualWarning",
    "FrameOrderWarning",
    "FrozenPixelsWarning",
    "ImageError",
    "LightPlacementWarning",
    "LightRigError",
    "ModelEvidenceWarning",
    "NearFieldDepthWarning",
    "OutputExistsError",
    "OutputPathError",
    "OutputWriteError",
    "InterreflectionWarning",
    "ParameterBoundWarning",
    "PipelineError",
    "PolarshapeError",
    "SelfCheckError",
    "ShapeError",
    "PolarshapeWarning",
    "SuspiciousInputWarning",
]


class PolarshapeError(Exception):
    """Every error a user can cause (a bad file, configuration, argument or device state).

    The message names the cause and the fix. The command line maps it to exit status 2 (1 for
    :class:`OutputExistsError`; 3 for :class:`PipelineError`, :class:`DeviceError` and
    :class:`OutputWriteError`) and prints ``error: <message>``, never a traceback.
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


class PolarshapeWarning(UserWarning):
    """Every warning polarshape issues on purpose (``warnings.warn``): the run goes on, but the user
    should look. The command line prints ``warning: <Kind>: <message>``; ``polarshape run`` also
    records each one in ``params.json`` (``warnings``)."""


class SuspiciousInputWarning(PolarshapeWarning):
    """An input that is valid but looks wrong (two lights with one direction, 12-bit data declared
    16-bit, ...); the message names the field, what looks wrong and what to check."""


# --- self-check warnings (polarshape.recover.selfcheck; each named in params.json "checks") -------


class FitResidualWarning(SuspiciousInputWarning):
    """The fitted model misses the observations by far more than the sensor noise (χ² against the
    capture's four-site noise model): the inputs do not describe the photographs — check the light
    directions (axes, signs), the frame order and the bit depth first, then the model."""


class ConventionWarning(SuspiciousInputWarning):
    """The polarisation azimuth (AoLP) disagrees with the azimuth of the photometric normals in a way
    one convention slip explains: it is mirrored (a light-direction axis flipped, or
    ``camera.mosaic.angles`` reversed), or the normals point inward at the silhouette (x and y of the
    lights both flipped); the message names the flip that fits."""


class FrameOrderWarning(SuspiciousInputWarning):
    """The frames' s0 fits the declared lights far better in another order: frames and lights are
    paired wrongly (shuffled file names, a rig that fired in another order); the message lists which
    frame looks lit by which light — fix ``lights[*].frame`` in capture.yaml."""


class LightPlacementWarning(SuspiciousInputWarning):
    """A point light sits where a lab rig's LED hardly can: behind the camera plane (z < 0 in the camera
    frame, z forward); usually the sign convention of z is flipped. The message names the lights."""


class NearFieldDepthWarning(PolarshapeWarning):
    """Near-field recovery could not estimate the object's absolute distance from the shading (fewer than
    4 point lights: every placement fits exactly; or an orthographic camera without a metric pixel size),
    so the depth stays at ``integration.reference_depth_m``; the message names the cause and the fix."""


class BitDepthWarning(SuspiciousInputWarning):
    """The counts do not fill the declared ``camera.bit_depth``: low-bit data declared deeper (12-bit
    counts declared 16-bit), or high-bit aligned data of a shallower ADC; the message names the bits
    the data look like and the fix (data deeper than declared are refused: a count above full scale)."""


class ParameterBoundWarning(PolarshapeWarning):
    """A fitted material parameter sits at the edge of the range the solver searches (e.g. β at 6, k_s
    at 0): the fit pushed against its limits because the model cannot explain the data as given —
    usually wrong inputs (see :class:`FitResidualWarning`), sometimes a material outside the model."""


class InterreflectionWarning(PolarshapeWarning):
    """Part of the object sees itself (a concavity) and receives light it reflects onto itself, which a
    fit of direct light explains by bending the normals there: give ``interreflection.albedo_scale``
    (the capture's albedo units per physical albedo, from a white reference target) so that the bounce
    is taken out, or read the marked pixels (``interreflection.npy``) with care."""


class ClippedLobeWarning(PolarshapeWarning):
    """The specular lobe's core is saturated wherever the object shows it (in every exposure): the
    fit sees only the lobe's flanks, so the fitted α, β and k_s are not identified (they drift to
    their bounds or trade off) — capture exposure brackets (``exposures_us``) or a shorter exposure."""


class FilledPixelsWarning(PolarshapeWarning):
    """A large fraction of the mask has too few usable observations and took its neighbours' normal
    and albedo (filled.png): more lights, a better exposure or a tighter mask."""


class FrozenPixelsWarning(PolarshapeWarning):
    """Most normals of the FMBRDF fit did not move from their photometric-stereo start: the joint fit
    did not run where it should (a fixed material that cannot explain the data, too few iterations)."""


class ModelEvidenceWarning(PolarshapeWarning):
    """On the lights held out of the fit, the Lambertian model predicts the photographs better than the
    FMBRDF the run used: the FMBRDF fit is not trustworthy here (params.json ``validation``)."""


class SelfCheckError(PolarshapeError, RuntimeError):
    """``polarshape run --strict``: a self-check warned. The result folder is still written (to look
    at); the message names the warnings and the folder. Exit status 4."""


class DeviceError(PolarshapeError, RuntimeError):
    """The torch device asked for cannot be used here (``cuda`` with a CPU-only torch or no GPU); the
    message names the field and the fix (``--device cpu`` / ``device: cpu`` or ``auto``). Exit status 3."""


class OutputWriteError(PolarshapeError, OSError):
    """An output could not be written (no space left on the device, no permission to create the
    folder); the message names the path, the cause and the fix. Exit status 3; nothing half-written is kept.

    Attributes:
        errno: the ``errno`` of the ``OSError`` behind it (``errno.ENOSPC``, ``errno.EACCES``, ...), or None.
        path: the output that could not be written, or None.
    """

    def __init__(self, message: str, *, errno: int | None = None, path: str | None = None) -> None:
        super().__init__(message)
        self.errno = errno
        self.path = path


class OutputPathError(PolarshapeError, NotADirectoryError):
    """An output path cannot be a folder: a file stands where one of its folders must be; the
    message names that file. Exit status 2 (invalid argument)."""
