"""``polarshape run CONFIG.yaml [--out DIR] [--overwrite]``: the main command (see polarshape.pipeline).

Registered on the main parser by :func:`add_parsers`. Exit status (see :mod:`polarshape.cli.errors`):
0 success, 1 refused to write over an existing folder or an input, 2 invalid configuration or input,
3 cannot run (a PipelineError, a builtin ValueError/OSError raised by a stage, no CUDA, a full or
read-only disk), 130 Ctrl-C, 143 SIGTERM.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from polarshape.cli import add_output_options
from polarshape.cli.errors import reports_errors
from polarshape.io.atomic import check_destination

__all__ = ["add_parsers", "refuse_existing_out"]


def _may_be_an_input(out: Path, config_path: Path) -> bool:
    """Whether ``out`` may be, hold or lie inside the run's input, as far as can be told without
    reading the configuration: it holds capture.yaml, it or a folder above it holds one, or it is or
    holds the configuration file. Then only :func:`polarshape.io.results.output_refusal` (after the
    configuration is read) gives the right reason."""
    out, config_path = out.absolute(), config_path.absolute()
    if any((folder / "capture.yaml").exists() for folder in (out, *out.parents)):
        return True
    return config_path == out or out in config_path.parents


def refuse_existing_out(out: str | None, config_path: str, *, overwrite: bool) -> None:
    """Refuse an existing ``--out`` (without ``--overwrite``) at once, before the configuration is
    read and torch is imported: the same refusal, with the same message, as the result folder's
    write (:func:`polarshape.io.atomic.atomic_directory`) gives once the run starts. A folder that
    may be an input is left to that check, which names the input.

    Raises:
        OutputExistsError: ``out`` exists and ``overwrite`` is False (exit status 1).
    """
    if out is None or overwrite:
        return
    path = Path(out).absolute()
    if not _may_be_an_input(path, Path(config_path)):
        check_destination(path, overwrite=False)


@reports_errors(builtin_status=3)
def _cmd_run(args: argparse.Namespace) -> int:
    refuse_existing_out(args.out, args.config, overwrite=args.overwrite)  # before torch is even imported
    from polarshape.checks import resolve_device
    from polarshape.config import load_run_config

    if args.device is not None:
        resolve_device(args.device, "--device")  # no CUDA: said before the configuration is even read
    config = load_run_config(args.config)
    from polarshape.pipeline import run_pipeline  # refuses an output it may not write before any stage
    updates: dict[str, Any] = {}
    if args.device is not None:
        updates["device"] = args.device
    if getattr(args, "quiet", False):  # set by polarshape.cli.main; absent when -q was not given
        updates["progress"] = False
    if updates:
        config = config.model_copy(update=updates)
    result = run_pipeline(config, args.out, overwrite=args.overwrite, config_path=args.config,
                          strict=getattr(args, "strict", False))
    print(result.summary)
    return 0


def add_parsers(sub: Any) -> None:
    """Register the ``run`` sub-command on the main parser's sub-parsers."""
    run = sub.add_parser(
        "run",
        help="run the whole pipeline on a capture (or a simulated/recorded one) as CONFIG describes",
        description="Recover normals, reflectance, depth and a mesh from a capture as the run configuration "
        "CONFIG.yaml describes (input, preprocess, initial normals, reflectometry + joint refinement, integration, "
        "mesh, export, report; see configs/default.yaml and configs/real_capture_template.yaml). The result folder "
        "is written atomically: it appears only when complete, and it never replaces an input or, without "
        "--overwrite, an existing folder. Prints the result folder and a one-line summary.",
    )
    run.add_argument("config", help="run configuration YAML (relative paths in it start at its folder)")
    run.add_argument("--out", default=None, metavar="DIR", help="result folder (default: output: in the config)")
    run.add_argument("--overwrite", action="store_true", help="replace an existing result folder (never an input)")
    run.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None,
                     help="torch device (default: device: in the config, auto = cuda when available)")
    run.add_argument("--strict", action="store_true",
                     help="a self-check warning (fit residual, conventions, frame order, bounds, ...) is an error: "
                     "the result folder is still written, the command exits with status 4")
    add_output_options(run, depth=1)  # -v/-q here too, so that this parser works on its own
    run.set_defaults(handler=_cmd_run)
