"""The one place where the command line turns an error into a message and an exit status.

Every sub-command handler (``_cmd_<name>(args) -> int``) is wrapped by :func:`reports_errors`;
handlers themselves never catch errors. Exit statuses (:data:`EXIT_STATUS_HELP`, also shown by
``polarshape --help``):

* 0 — success (the handler's own return value);
* 1 — refused: :class:`~polarshape.errors.OutputExistsError` (would write over an existing folder,
  an input, or something that is not polarshape's);
* 2 — invalid input: any other :class:`~polarshape.errors.PolarshapeError` (configuration, scene,
  capture, image, camera, light rig, argument, an output path through a file);
* 3 — cannot run: :class:`~polarshape.errors.PipelineError` (a stage of ``polarshape run`` failed),
  :class:`~polarshape.errors.DeviceError` (no CUDA), :class:`~polarshape.errors.OutputWriteError`
  (the disk is full or the folder is not writable), and a builtin ``OSError`` saying so (ENOSPC,
  EDQUOT, EROFS);
* 4 — ``polarshape run --strict``: a self-check warned (:class:`~polarshape.errors.SelfCheckError`);
  the result folder is written before, so it can be looked at;
  ``polarshape batch``: some captures failed (the others' results and ``failed.json`` are written);
* a builtin ``ValueError`` or ``OSError`` (a bad value or an unreadable file that no polarshape
  check named): ``builtin_status``, 2 unless the command says otherwise (``run``: 3, a stage failed);
* 130 — interrupted by Ctrl-C (:func:`polarshape.cli.main`); nothing half-written is kept;
* 143 — terminated by SIGTERM (``kill``, ``timeout``), likewise.

Each prints ``error: <message>`` on stderr, never a traceback (``-vv`` logs the traceback at
debug level). ``KeyboardInterrupt`` and programming errors (``TypeError``, ...) propagate.
"""

from __future__ import annotations

import errno
import functools
import logging
import sys
from collections.abc import Callable
from typing import Any

from polarshape.errors import (
    DeviceError, OutputExistsError, OutputWriteError, PipelineError, PolarshapeError, SelfCheckError,
)

__all__ = ["EXIT_STATUS", "EXIT_STATUS_HELP", "exit_status", "reports_errors"]

logger = logging.getLogger(__name__)

#: Exit status by error kind; the first kind the error is an instance of wins (so the subclass
#: OutputExistsError comes before its base class).
EXIT_STATUS: tuple[tuple[type[PolarshapeError], int], ...] = (
    (OutputExistsError, 1),
    (SelfCheckError, 4),
    (PipelineError, 3),
    (DeviceError, 3),
    (OutputWriteError, 3),
    (PolarshapeError, 2),
)

#: errno values of a builtin OSError that mean "cannot write here", whatever the command (status 3).
CANNOT_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS})

#: The exit-status table, as ``polarshape --help`` and every sub-command's ``--help`` end.
EXIT_STATUS_HELP = """exit status:
  0    success
  1    refused: would write over an existing folder, an input, or not ours
  2    invalid input: configuration, scene, capture, image or argument
  3    cannot run: a stage failed, the disk is full or not writable, no CUDA
  4    run --strict: a self-check failed (result kept); batch: some captures failed
  130  interrupted (Ctrl-C); nothing half-written is kept
  143  terminated (SIGTERM); nothing half-written is kept"""

Handler = Callable[[Any], int]


def exit_status(exc: BaseException, builtin_status: int = 2) -> int | None:
    """The exit status for ``exc`` (see the module docstring), or None if it is not reported."""
    for kind, status in EXIT_STATUS:
        if isinstance(exc, kind):
            return status
    if isinstance(exc, OSError) and exc.errno in CANNOT_WRITE_ERRNOS:
        return 3
    if isinstance(exc, (ValueError, OSError)):
        return builtin_status
    return None


def reports_errors(builtin_status: int = 2) -> Callable[[Handler], Handler]:
    """Decorate a sub-command handler: errors become ``error: <message>`` on stderr and an exit status.

    Args:
        builtin_status: exit status for a builtin ``ValueError``/``OSError`` (2: invalid input;
            ``run`` passes 3, because there such an error comes from a stage that failed).
    """

    def decorate(handler: Handler) -> Handler:
        @functools.wraps(handler)
        def wrapper(args: Any) -> int:
            try:
                return handler(args)
            except Exception as exc:
                status = exit_status(exc, builtin_status)
                if status is None:
                    raise
                logger.debug("%s failed", handler.__name__, exc_info=True)
                print(f"error: {exc}", file=sys.stderr)
                return status

        return wrapper

    return decorate
