"""``polarshape material CAPTURE --shape sphere|normals.npy|mesh.ply [--pose P] [--frames I ...] [--models M,...] [--out DIR]``
and ``polarshape material --brdf-table FILE.binary [--kappa] [--out DIR]``.

The material of an object of known geometry (see :mod:`polarshape.measure`): every model fitted by
the paper's eq. 25, OUT/material.json (the FMBRDF fit) and OUT/report.html; or the FMBRDF fitted to a
MERL table (:func:`polarshape.measure.measure_table`). Registered on the main
parser by :func:`add_parsers`. Exit status (:mod:`polarshape.cli.errors`): 0 success, 1 refused to
write over an existing folder or an input, 2 invalid capture, shape, frames or models, 3 cannot
write the result.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from polarshape.cli.errors import reports_errors
from polarshape.errors import ConfigError
from polarshape.io.atomic import check_destination

__all__ = ["DEFAULT_MODELS", "add_parsers", "parse_models"]

#: polarshape.recover.material_fit.FIT_MODELS, written out so that parsing does not import torch.
DEFAULT_MODELS = "fmbrdf,baek,on_ts,l_ts"


def parse_models(text: str) -> tuple[str, ...]:
    """``"fmbrdf,baek"`` → ("fmbrdf", "baek"); names are checked by :func:`polarshape.measure.measure_material`."""
    models = tuple(m.strip() for m in text.split(",") if m.strip())
    if not models:
        raise ConfigError("--models: give a comma-separated list, e.g. --models fmbrdf,baek,on_ts,l_ts")
    return models


def _cmd_table(args: argparse.Namespace) -> int:
    """``polarshape material --brdf-table FILE``: the FMBRDF fitted to a MERL table."""
    if args.capture is not None or args.shape is not None:
        raise ConfigError("polarshape material: give either CAPTURE --shape ... or --brdf-table FILE, not both")
    table = Path(args.brdf_table)
    out = Path(args.out) if args.out is not None else table.absolute().parent / (table.stem + "_material")
    if not args.overwrite:
        check_destination(out.absolute(), overwrite=False)  # before torch is imported
    from polarshape.measure import measure_table

    print(measure_table(table, out=out, overwrite=args.overwrite, fit_kappa=args.kappa)[2])
    return 0


@reports_errors(builtin_status=2)
def _cmd_material(args: argparse.Namespace) -> int:
    if args.brdf_table is not None:
        return _cmd_table(args)
    if args.capture is None:
        raise ConfigError("polarshape material: give a CAPTURE folder (with --shape), or --brdf-table FILE")
    out = Path(args.out) if args.out is not None else Path(args.capture).absolute().parent / (
        Path(args.capture).absolute().name + "_material")
    if not args.overwrite and not (out.absolute() / "capture.yaml").exists():
        # an existing folder is refused before torch is imported (a capture there: measure names the input)
        check_destination(out.absolute(), overwrite=False)
    if args.shape is None:
        raise ConfigError("polarshape material: give --shape sphere, --shape NORMALS.npy or --shape MESH.ply --pose POSE")
    models = parse_models(args.models)
    from polarshape.measure import measure_material

    result = measure_material(args.capture, shape=args.shape, out=out, frames=args.frames, models=models,
                              overwrite=args.overwrite, held_out=not args.no_held_out, pose=args.pose,
                              pixel_size_m=args.pixel_size_m)
    print(result.summary)
    return 0


def add_parsers(sub: Any) -> None:
    """Register the ``material`` sub-command on the main parser's sub-parsers."""
    p = sub.add_parser(
        "material",
        help="fit the material of an object of known geometry (sphere, normal map, mesh) or of a MERL table",
        description="Fit the Fresnel Microfacet BRDF and the baselines (Baek et al. pBRDF, Oren-Nayar + "
        "Torrance-Sparrow, Lambertian + Torrance-Sparrow) to a capture of an object whose shape is known, by the "
        "paper's eq. 25 (intensity + DoLP with outlier weights). Writes OUT/material.json (the FMBRDF fit, with every "
        "model's parameters and errors under 'fit') and OUT/report.html (observed vs fitted intensity and DoLP "
        "curves, parameter tables, and with several frames each frame predicted from a fit to the others).",
    )
    p.add_argument("capture", nargs="?", default=None,
                   help="capture folder (capture.yaml, frames/, mask.png); not with --brdf-table")
    p.add_argument("--brdf-table", default=None, metavar="FILE",
                   help="instead of a capture: fit the FMBRDF's intensity to a tabulated isotropic BRDF in the MERL "
                   "binary layout (90x90x180), by the log-RMSE; writes OUT/material.json")
    p.add_argument("--kappa", action="store_true", help="--brdf-table: fit kappa too (5-10x slower)")
    p.add_argument("--shape", default=None, metavar="sphere|NORMALS.npy|MESH.ply",
                   help="'sphere' (fitted to the capture's mask), a camera-frame normal map (H/2, W/2, 3) .npy, or a "
                   "mesh (.ply/.obj/.stl/.off/.glb, metres) placed by --pose")
    p.add_argument("--pose", default=None, metavar="POSE",
                   help="mesh only: object -> camera transform, a 4x4 or 3x4 (R|t) matrix in a .npy or text file "
                   "(camera frame: x right, y down, z into the scene; metres)")
    p.add_argument("--pixel-size-m", type=float, default=None, metavar="M",
                   help="mesh in an orthographic capture: metres per raw pixel (default: the simulated scene's)")
    p.add_argument("--frames", type=int, nargs="+", default=None, metavar="I",
                   help="frame indices to use, in capture.yaml's order (default: all)")
    p.add_argument("--models", default=DEFAULT_MODELS,
                   help=f"comma-separated models to fit (default {DEFAULT_MODELS}; also lambertian, oren_nayar, "
                   "torrance_sparrow)")
    p.add_argument("--no-held-out", action="store_true",
                   help="skip the leave-one-frame-out predictions (faster with many frames)")
    p.add_argument("--out", default=None, metavar="DIR", help="result folder (default: CAPTURE_material beside it)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing material folder (never an input)")
    p.set_defaults(handler=_cmd_material)
