"""``polarshape run CONFIG.yaml [--out DIR] [--overwrite]``: the main command (see polarshape.pipeline).

Registered on the main parser by :func:`add_parsers`. Exit status (see :mod:`polarshape.cli.errors`):
0 success, 1 refused to write over an existing folder or an input, 2 invalid configuration or input,
3 cannot run (a PipelineError, a builtin ValueError/OSError raised by a stage, no CUDA, a full or
read-only disk), 130 Ctrl-C, 143 SIGTERM.
"""

from __future__ import annotations

import argparse
from typing import Any

from polarshape.cli.errors import reports_errors


@reports_errors(builtin_status=3)
def _cmd_run(args: argparse.Namespace) -> int:
    from polarshape.checks import resolve_device
    from polarshape.config import load_run_config
    from polarshape.pipeline import run_pipeline

    if args.device is not None:
        resolve_device(args.device, "--device")  # no CUDA: said before the configuration is even read
    config = load_run_config(args.config)
    updates: dict[str, Any] = {}
    if args.device is not None:
        updates["device"] = args.device
    if args.quiet:
        updates["progress"] = False
    if updates:
        config = config.model_copy(update=updates)
    result = run_pipeline(config, args.out, overwrite=args.overwrite, config_path=args.config)
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
    run.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    run.set_defaults(handler=_cmd_run)
