"""The one function every batch engine runs per capture: :func:`run_capture`.

It runs the pipeline of one capture into ``DIR/<name>`` exactly as ``polarshape run`` would write it
(atomically, with its log in ``run.log`` inside the result), and never raises for a failing capture:
the error comes back in the :class:`CaptureOutcome`, so one bad capture never stops the others.
Inputs are read and results written by the process that runs it, so on a cluster both must be on
a filesystem path every node sees.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import time
import traceback
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch

from polarshape.cli.errors import exit_status
from polarshape.config import BatchConfig
from polarshape.errors import PolarshapeError
from polarshape.pipeline import run_pipeline

__all__ = ["LOG_FILE", "CaptureOutcome", "CaptureTask", "error_record", "run_capture"]

logger = logging.getLogger(__name__)

#: The per-capture log, inside each result folder.
LOG_FILE = "run.log"


@dataclass(frozen=True)
class CaptureTask:
    """One capture of a batch, as a worker receives it (picklable: it travels to other processes).

    Attributes:
        name: the capture's name (its result is ``out_dir``).
        capture: the capture folder (absolute).
        out_dir: the result folder ``DIR/<name>`` (absolute).
        config: the batch configuration (``input`` is set to ``capture``).
        config_path: the batch configuration file (protected, named in messages), or None.
        overwrite: replace an existing result.
        threads: torch threads of the run.
    """

    name: str
    capture: str
    out_dir: str
    config: BatchConfig
    config_path: str | None = None
    overwrite: bool = False
    threads: int = 1


@dataclass(frozen=True)
class CaptureOutcome:
    """What :func:`run_capture` returns.

    Attributes:
        name, capture: as in the task.
        ok: the result folder was written.
        seconds: wall time of the call in the worker (configuration, pipeline, writing).
        params: the result's params.json content (None when it failed).
        error: :func:`error_record` of the failure (None when ok).
        worker: ``host:pid`` of the process that ran it.
    """

    name: str
    capture: str
    ok: bool
    seconds: float
    params: dict[str, Any] | None = None
    error: dict[str, Any] | None = None
    worker: str = ""


def error_record(exc: BaseException) -> dict[str, Any]:
    """failed.json's record of ``exc``: its kind, message, the exit status ``polarshape run`` would
    give it, and the traceback when it is not an error polarshape raises on purpose (a bug to report)."""
    status = exit_status(exc, builtin_status=3)
    record: dict[str, Any] = {"type": type(exc).__name__, "message": str(exc), "exit_status": status}
    if not isinstance(exc, PolarshapeError):
        record["traceback"] = "".join(traceback.format_exception(exc))
    return record


def _log_warning(message: Warning | str, category: type[Warning], *args: Any, **kwargs: Any) -> None:
    logger.warning("%s: %s", category.__name__, message)


@contextlib.contextmanager
def _logs_to_result_only() -> Iterator[None]:
    """While a capture runs in a worker, polarshape's log records (INFO and above) and warnings go to
    its run.log, not to the console the workers share (the pipeline still records the warnings in
    params.json; the batch's progress bar and summary say the rest). Restored afterwards."""
    package = logging.getLogger("polarshape")
    level, propagate = package.level, package.propagate
    package.setLevel(logging.INFO)
    package.propagate = False
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _log_warning
            yield
    finally:
        package.setLevel(level)
        package.propagate = propagate


@contextlib.contextmanager
def _torch_threads(threads: int) -> Iterator[None]:
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def run_capture(task: CaptureTask) -> CaptureOutcome:
    """Run one capture of a batch (every engine calls this, in its worker process).

    Returns a failed :class:`CaptureOutcome` for any error of the capture (an invalid capture, a
    stage that fails, an existing folder that is not a result, a bug); only an interruption
    (``KeyboardInterrupt``, ``SystemExit``) propagates, after the half-written folder is removed.
    """
    t0 = time.perf_counter()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    with _logs_to_result_only(), _torch_threads(task.threads):
        try:
            config = task.config.for_capture(task.capture, source=task.config_path or "batch configuration")
            result = run_pipeline(config, task.out_dir, overwrite=task.overwrite, config_path=task.config_path,
                                  log_file=LOG_FILE)
        except Exception as exc:  # noqa: BLE001 - recorded, and the batch goes on
            logger.debug("capture %s failed", task.name, exc_info=True)
            return CaptureOutcome(task.name, task.capture, ok=False, seconds=time.perf_counter() - t0,
                                  error=error_record(exc), worker=worker)
    return CaptureOutcome(task.name, task.capture, ok=True, seconds=time.perf_counter() - t0, params=result.params,
                          worker=worker)
