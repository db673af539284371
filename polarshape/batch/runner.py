"""``polarshape batch``: every capture of a batch through one configuration, into ``DIR/<capture name>``.

The batch folder ``DIR`` holds ``batch.json`` (what it is: format :data:`BATCH_FORMAT`), one result
folder per capture (exactly what ``polarshape run`` writes, with its log in ``run.log``),
``summary.csv`` + ``index.html`` (one row per capture, :mod:`polarshape.batch.summary`) and
``failed.json``. It is resumable: a capture whose result folder is complete
(:func:`polarshape.io.results.is_result_folder`) is skipped unless ``overwrite``; a failed or
missing one is run again. A failing capture never stops the others.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from polarshape import __version__
from polarshape.batch.captures import BATCH_FILES
from polarshape.batch.engines import ENGINES, plan_local, run_local, run_ray
from polarshape.batch.summary import read_failed, summary_row, write_failed, write_summary
from polarshape.batch.worker import CaptureOutcome, CaptureTask
from polarshape.checks import resolve_device
from polarshape.config import BatchConfig
from polarshape.errors import ConfigError, OutputExistsError
from polarshape.io.atomic import atomic_write_text, remove_stale_temporaries
from polarshape.io.results import is_result_folder, output_refusal

__all__ = ["BATCH_FORMAT", "BatchResult", "is_batch_folder", "run_batch"]

logger = logging.getLogger(__name__)

#: Format tag of batch.json, the mark of a batch folder.
BATCH_FORMAT = "polarshape-batch/1"


@dataclass(frozen=True)
class BatchResult:
    """What :func:`run_batch` returns.

    Attributes:
        out_dir: the batch folder.
        rows: summary.csv's rows, in capture order (:func:`polarshape.batch.summary.summary_row`).
        seconds: wall time of the batch.
        engine: ``local`` or ``ray``; workers: local workers (None for Ray); threads: per run.
    """

    out_dir: Path
    rows: list[dict[str, Any]]
    seconds: float
    engine: str
    workers: int | None = None
    threads: int = 1
    outcomes: list[CaptureOutcome] = field(default_factory=list, repr=False)

    def count(self, status: str) -> int:
        """How many captures have ``status`` (done, complete, failed, pending)."""
        return sum(row["status"] == status for row in self.rows)

    @property
    def failed(self) -> int:
        return self.count("failed")

    @property
    def summary(self) -> str:
        """One line: where, how many done / skipped / failed, where the tables are, time."""
        parts = [f"batch in {self.out_dir}", f"{len(self.rows)} captures", f"{self.count('done')} done"]
        if self.count("complete"):
            parts.append(f"{self.count('complete')} complete from an earlier run (skipped)")
        if self.failed:
            parts.append(f"{self.failed} failed (see {self.out_dir / 'failed.json'})")
        parts += [f"summary {self.out_dir / 'summary.csv'}", f"{self.seconds:.1f} s"]
        return "; ".join(parts)


def is_batch_folder(path: Path) -> bool:
    """True when ``path`` holds a batch.json of format :data:`BATCH_FORMAT`."""
    try:
        return json.loads((path / "batch.json").read_text()).get("format") == BATCH_FORMAT
    except (OSError, ValueError, AttributeError):
        return False


def _check_out(out: Path, captures: Mapping[str, Path], config_path: str | None) -> None:
    """Refuse a batch folder that is, holds or lies inside an input, or an existing folder that is
    neither empty nor a batch folder (its files might be the user's)."""
    reason = output_refusal(out, [*captures.values(), config_path], overwrite=False)
    if reason:
        raise OutputExistsError(f"{out}: {reason}; refusing to write there (choose another --out)")
    if out.exists() and not out.is_dir():
        raise OutputExistsError(f"{out} exists and is not a folder; choose another --out")
    if out.is_dir() and any(out.iterdir()) and not is_batch_folder(out):
        raise OutputExistsError(f"{out} exists and is not a polarshape batch folder (no batch.json of format "
                                f"{BATCH_FORMAT}); choose another --out, or an empty or earlier batch folder")


def _tasks(config: BatchConfig, captures: Mapping[str, Path], out: Path, *, overwrite: bool, threads: int,
           config_path: str | None) -> tuple[dict[str, dict[str, Any]], list[CaptureTask]]:
    """Rows of the captures complete from an earlier run (skipped unless ``overwrite``), and the
    tasks of the others."""
    rows: dict[str, dict[str, Any]] = {}
    tasks = []
    for name, capture in captures.items():
        result = out / name
        if not overwrite and is_result_folder(result):
            rows[name] = summary_row(name, capture, "complete", json.loads((result / "params.json").read_text()))
            continue
        rows[name] = summary_row(name, capture, "pending")
        tasks.append(CaptureTask(name, str(capture), str(result), config, config_path, overwrite, threads))
    return rows, tasks


def _engine_outcomes(engine: str, tasks: list[CaptureTask], workers: int | None, address: str | None,
                     device: str) -> Iterator[CaptureOutcome]:
    if engine == "local":
        return run_local(tasks, workers or 1)
    return run_ray(tasks, address=address, device=device)


def run_batch(
    config: BatchConfig,
    captures: Mapping[str, Path],
    out_dir: str | os.PathLike[str],
    *,
    engine: str = "local",
    workers: int | None = None,
    threads_per_worker: int | None = None,
    address: str | None = None,
    overwrite: bool = False,
    config_path: str | os.PathLike[str] | None = None,
    progress: bool = True,
) -> BatchResult:
    """Run every capture through ``config`` into ``out_dir/<name>``; see the module docstring.

    Args:
        config: the batch configuration (:func:`polarshape.config.load_batch_config`).
        captures: name → capture folder (:func:`polarshape.batch.find_captures`).
        out_dir: the batch folder (created; an earlier batch folder is resumed).
        engine: ``local`` (a process pool) or ``ray`` (:mod:`polarshape.batch.engines`).
        workers, threads_per_worker: local pool size and torch threads per run (default: one thread,
            one worker per core; :func:`~polarshape.batch.engines.plan_local`); Ray: threads = ``num_cpus``.
        address: Ray cluster address (None: ``RAY_ADDRESS``, a cluster on this machine, or a local instance).
        overwrite: run every capture again, replacing its result (never anything that is not a result).
        config_path: the configuration file (recorded, protected from being overwritten).
        progress: one progress bar over the captures.

    Returns:
        :class:`BatchResult`; ``result.failed`` captures failed (their errors are in failed.json).

    Raises:
        OutputExistsError: ``out_dir`` is an input, or an existing folder that is not a batch folder.
        ConfigError: an unknown engine, or workers × threads over the cores. DeviceError: no CUDA
            (local) or no GPU in the cluster for ``device: cuda``. PipelineError: Ray is not installed.
    """
    t0 = time.perf_counter()
    if engine not in ENGINES:
        raise ConfigError(f"--engine must be one of {', '.join(ENGINES)}; got {engine!r}")
    out = Path(out_dir).absolute()
    path = None if config_path is None else str(Path(config_path).absolute())
    _check_out(out, captures, path)
    if engine == "local":
        resolve_device(config.device, "device")  # no CUDA: said once, before any capture
        workers, threads = plan_local(len(captures), workers, threads_per_worker)
    else:
        workers, threads = None, threads_per_worker or 1
    out.mkdir(parents=True, exist_ok=True)
    for name in BATCH_FILES:  # the tables' temporaries a batch killed outright left
        remove_stale_temporaries(out / name)
    atomic_write_text(out / "batch.json", json.dumps({
        "format": BATCH_FORMAT, "polarshape_version": __version__, "config": path, "engine": engine,
        "captures": {name: str(folder) for name, folder in captures.items()},
    }, indent=1) + "\n", overwrite=True)
    rows, tasks = _tasks(config, captures, out, overwrite=overwrite, threads=threads, config_path=path)
    failures = {name: record for name, record in read_failed(out).items() if name in captures and
                rows[name]["status"] == "pending"}  # earlier failures, until they are run again
    write_summary(out, list(rows.values()))
    write_failed(out, _in_order(failures, captures))
    logger.info("batch: %d captures, %d to run (%s engine%s, %d thread(s) per run)", len(captures), len(tasks),
                engine, f", {workers} workers" if workers else "", threads)
    outcomes: list[CaptureOutcome] = []
    bar = tqdm(total=len(captures), initial=len(captures) - len(tasks), desc="polarshape batch", unit="capture",
               disable=not progress)
    try:
        with logging_redirect_tqdm(), contextlib.closing(
                _engine_outcomes(engine, tasks, workers, address, config.device)) as finished:
            for outcome in finished:
                outcomes.append(outcome)
                _record(outcome, rows, failures)
                write_summary(out, list(rows.values()))
                write_failed(out, _in_order(failures, captures))
                bar.update(1)
                bar.set_postfix_str(f"{len(failures)} failed" if failures else "")
    finally:
        bar.close()
    return BatchResult(out, list(rows.values()), time.perf_counter() - t0, engine, workers, threads, outcomes)


def _in_order(failures: Mapping[str, dict[str, Any]], captures: Mapping[str, Path]) -> dict[str, dict[str, Any]]:
    return {name: failures[name] for name in captures if name in failures}


def _record(outcome: CaptureOutcome, rows: dict[str, dict[str, Any]], failures: dict[str, dict[str, Any]]) -> None:
    """Put a finished capture into the summary rows and the failures."""
    name = outcome.name
    if outcome.ok:
        rows[name] = summary_row(name, outcome.capture, "done", outcome.params)
        failures.pop(name, None)
        logger.info("capture %s: done in %.1f s", name, outcome.seconds)
        return
    error = outcome.error or {}
    rows[name] = summary_row(name, outcome.capture, "failed", error=error, seconds=outcome.seconds)
    failures[name] = {"source": outcome.capture, **error, "seconds": outcome.seconds, "worker": outcome.worker}
    logger.warning("capture %s failed: %s: %s", name, error.get("type"), error.get("message"))
