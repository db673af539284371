"""Many captures through one pipeline configuration: ``polarshape batch CONFIG CAPTURES... --out DIR``.

* :mod:`~polarshape.batch.captures` — :func:`find_captures`: folders and globs → named capture folders;
* :mod:`~polarshape.batch.worker` — :func:`run_capture`: the one function every engine runs per capture;
* :mod:`~polarshape.batch.engines` — where it runs: a local process pool or a Ray cluster;
* :mod:`~polarshape.batch.summary` — summary.csv, index.html, failed.json;
* :mod:`~polarshape.batch.runner` — :func:`run_batch`: the batch folder, resume, progress.

Example:
    >>> from polarshape.config import load_batch_config
    >>> result = run_batch(load_batch_config("batch.yaml"), find_captures(["captures/*"]), "results/batch")  # doctest: +SKIP
    >>> result.failed, result.rows[0]["normal_mean_deg"]  # doctest: +SKIP
"""

from polarshape.batch.captures import BATCH_FILES, find_captures
from polarshape.batch.engines import ENGINES, RAY_INSTALL_HINT, available_cores, plan_local, ray_uses_gpus
from polarshape.batch.runner import BATCH_FORMAT, BatchResult, is_batch_folder, run_batch
from polarshape.batch.summary import FAILED_FORMAT, STATUSES, SUMMARY_COLUMNS, read_failed, summary_row
from polarshape.batch.worker import LOG_FILE, CaptureOutcome, CaptureTask, run_capture

__all__ = [
    "BATCH_FILES", "BATCH_FORMAT", "ENGINES", "FAILED_FORMAT", "LOG_FILE", "RAY_INSTALL_HINT", "STATUSES",
    "SUMMARY_COLUMNS", "BatchResult", "CaptureOutcome", "CaptureTask", "available_cores", "find_captures",
    "is_batch_folder", "plan_local", "ray_uses_gpus", "read_failed", "run_batch", "run_capture", "summary_row",
]
