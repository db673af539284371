"""``polarshape batch CONFIG.yaml CAPTURES... --out DIR``: many captures through one configuration
(see :mod:`polarshape.batch`).

Registered on the main parser by :func:`add_parsers`. Exit status (see :mod:`polarshape.cli.errors`):

* 0 — every capture has a complete result (run now or by an earlier batch);
* 4 — :data:`SOME_FAILED`: some captures failed (each recorded in ``DIR/failed.json`` and
  ``DIR/summary.csv``; the others were still run; the same command retries the failed ones);
* 1 — refused: ``DIR`` is an input, or an existing folder that is not a batch folder;
* 2 — invalid input: the configuration (or an ``input`` section in it), a capture path or pattern,
  ``--workers`` × ``--threads-per-worker`` over the cores;
* 3 — cannot run: no CUDA for ``device: cuda``, Ray not installed for ``--engine ray``;
* 130 / 143 — Ctrl-C / SIGTERM: the complete results are kept, nothing half-written is, and the
  same command resumes.
"""

from __future__ import annotations

import argparse
from typing import Any

from polarshape.cli import add_output_options
from polarshape.cli.errors import reports_errors

__all__ = ["SOME_FAILED", "add_parsers"]

#: Exit status of a batch in which some captures failed.
SOME_FAILED = 4

@reports_errors(builtin_status=3)
def _cmd_batch(args: argparse.Namespace) -> int:
    from polarshape.batch import find_captures, run_batch
    from polarshape.config import load_batch_config

    config = load_batch_config(args.config)
    captures = find_captures(args.captures)
    updates: dict[str, Any] = {"progress": False}  # one bar over the captures, none per run
    if args.device is not None:
        updates["device"] = args.device
    progress = config.progress and not getattr(args, "quiet", False)
    result = run_batch(
        config.model_copy(update=updates), captures, args.out, engine=args.engine, workers=args.workers,
        threads_per_worker=args.threads_per_worker, address=args.address, overwrite=args.overwrite,
        config_path=args.config, progress=progress,
    )
    print(result.summary)
    return SOME_FAILED if result.failed else 0


def add_parsers(sub: Any) -> None:
    """Register the ``batch`` sub-command on the main parser's sub-parsers."""
    batch = sub.add_parser(
        "batch",
        help="run many captures through one configuration, on this machine or a Ray cluster (resumable)",
        description="Run every capture through the pipeline that CONFIG.yaml describes (a run configuration without "
        "input), each into DIR/<capture name>/ exactly as `polarshape run` writes it. A re-run skips the captures "
        "whose result is complete and retries the others; a failing capture never stops the others. DIR gets "
        "summary.csv, index.html (links to every report) and failed.json. Exit status 4: some captures failed.",
    )
    batch.add_argument("config", metavar="CONFIG", help="run configuration YAML without input (relative paths start at its folder)")
    batch.add_argument("captures", nargs="+", metavar="CAPTURE",
                       help="capture folders or glob patterns (quote them: 'captures/*')")
    batch.add_argument("--out", required=True, metavar="DIR", help="batch folder (an earlier one is resumed)")
    batch.add_argument("--overwrite", action="store_true",
                       help="run every capture again, replacing its result (never anything that is not a result)")
    batch.add_argument("--engine", choices=["local", "ray"], default="local",
                       help="local: a process pool on this machine (default); ray: tasks on a Ray cluster "
                       "(pip install 'polarshape[cluster]')")
    batch.add_argument("--address", default=None,
                       help="Ray cluster address (HOST:PORT of `ray start --head`, or ray://...; default: "
                       "RAY_ADDRESS, a cluster on this machine, else a local Ray instance)")
    batch.add_argument("--workers", type=int, default=None, metavar="N",
                       help="local: worker processes (default: cores // threads per worker)")
    batch.add_argument("--threads-per-worker", type=int, default=None, metavar="N",
                       help="torch threads per run (local default: cores // workers, else 1; ray: num_cpus per task, "
                       "default 1)")
    batch.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None,
                       help="torch device (default: device: in the config; ray: one GPU per task where the cluster "
                       "has GPUs)")
    add_output_options(batch, depth=1)
    batch.set_defaults(handler=_cmd_batch)
