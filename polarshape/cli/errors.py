"""The one place where the command line turns an error into a message and an exit status.

Every sub-command handler (``_cmd_<name>(args) -> int``) is wrapped by :func:`reports_errors`;
handlers themselves never catch errors. Exit statuses:

* 0 — success (the handler's own return value);
* 1 — :class:`~polarshape.errors.OutputExistsError`: refused to write over an existing folder or an input;
* 3 — :class:`~polarshape.errors.PipelineError`: a stage of ``polarshape run`` cannot run;
* 2 — any other :class:`~polarshape.errors.PolarshapeError` (invalid configuration, capture, image,
  camera, light rig or argument);
* a builtin ``ValueError`` or ``OSError`` (a bad value or an unreadable file that no polarshape
  check named): ``builtin_status``, 2 unless the command says otherwise (``run``: 3, a stage failed).

Each prints ``error: <message>`` on stderr, never a traceback (``-vv`` logs the traceback at
debug level). ``KeyboardInterrupt`` and programming errors (``TypeError``, ...) propagate.
"""

from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Callable
from typing import Any

from polarshape.errors import OutputExistsError, PipelineError, PolarshapeError

__all__ = ["EXIT_STATUS", "exit_status", "reports_errors"]

logger = logging.getLogger(__name__)

#: Exit status by error kind; the first kind the error is an instance of wins (so the subclass
#: OutputExistsError comes before its base class).
EXIT_STATUS: tuple[tuple[type[PolarshapeError], int], ...] = (
    (OutputExistsError, 1),
    (PipelineError, 3),
    (PolarshapeError, 2),
)

Handler = Callable[[Any], int]


def exit_status(exc: BaseException, builtin_status: int = 2) -> int | None:
    """The exit status for ``exc`` (see the module docstring), or None if it is not reported."""
    for kind, status in EXIT_STATUS:
        if isinstance(exc, kind):
            return status
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
