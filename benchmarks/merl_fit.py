"""Benchmark of the MERL-table export and fit (issue 19).

Reports, in one run on this machine:
1. the time to render an FMBRDF into the full 90×90×180 MERL table and to write and read it back;
2. for a few FMBRDF materials rendered into the table (RGB body albedos), the fit of
   :func:`polarshape.recover.table_fit.fit_fmbrdf_to_table` from the default start (coarse α search):
   wall time, model evaluations, the log-RMSE on the fit's samples and on the whole table, and the
   parameter errors;
3. with ``--merl FILE.binary`` (a measured MERL BRDF), the fit of that file instead.

Usage:  python benchmarks/merl_fit.py [--samples 20000] [--threads 2] [--kappa] [--merl FILE ...]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from polarshape.brdf import FMBRDFParams
from polarshape.brdf.tabulate import fmbrdf_merl_table
from polarshape.io.merl import MerlTable, read_merl, write_merl
from polarshape.recover.table_fit import fit_fmbrdf_to_table, log_rmse

MATERIALS = {
    "plastic": (FMBRDFParams(ior=1.5, alpha=0.12, beta=2.0, kappa=0.0, k_s=1.0, k_b=0.5), (0.6, 0.4, 0.1)),
    "rough": (FMBRDFParams(ior=1.6, alpha=0.45, beta=1.2, kappa=0.0, k_s=0.7, k_b=0.3), (0.3, 0.3, 0.35)),
    "correlated": (FMBRDFParams(ior=1.45, alpha=0.3, beta=2.0, kappa=30.0, k_s=0.9, k_b=0.4), (0.4, 0.5, 0.2)),
}


def full_table_log_rmse(values: np.ndarray, fitted: np.ndarray) -> float:
    """The log-RMSE over every cell valid in both tables (cos θ_i from the table geometry)."""
    from polarshape.brdf.tabulate import merl_directions

    cos_i = merl_directions()[0][..., 2]
    ok = (values >= 0).all(axis=0) & (fitted >= 0).all(axis=0)
    return log_rmse(values[:, ok], fitted[:, ok], cos_i[ok])


def report_fit(name: str, table: MerlTable, args: argparse.Namespace, truth: FMBRDFParams | None) -> None:
    fit = fit_fmbrdf_to_table(table, n_samples=args.samples, fit_kappa=args.kappa)
    fitted = fmbrdf_merl_table(fit.params, k_s_rgb=fit.k_s_rgb, k_b_rgb=fit.k_b_rgb)
    whole = full_table_log_rmse(table.values, fitted)
    p = fit.params
    line = (f"{name:12s} fit {fit.seconds:6.1f} s  {fit.n_evaluations:3d} evals  log-RMSE samples {fit.log_rmse:.3g}"
            f" (start {fit.log_rmse_init:.3g})  table {whole:.3g}  μ {p.ior:.3f} α {p.alpha:.3f} β {p.beta:.2f} κ {p.kappa:.1f}")
    if truth is not None:
        line += f"  | Δμ {p.ior - truth.ior:+.3f} α {100 * (p.alpha / truth.alpha - 1):+.1f}%"
    print(line)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=20_000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--kappa", action="store_true", help="fit κ too")
    ap.add_argument("--merl", nargs="*", default=[], help="measured MERL .binary files to fit")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    params, k_b_rgb = MATERIALS["plastic"]
    t0 = time.perf_counter()
    values = fmbrdf_merl_table(params, k_b_rgb=k_b_rgb)
    t1 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        path = write_merl(Path(tmp) / "plastic.binary", MerlTable.from_brdf(values))
        t2 = time.perf_counter()
        back = read_merl(path)
        t3 = time.perf_counter()
    print(f"render full table {t1 - t0:.2f} s, write {t2 - t1:.2f} s, read {t3 - t2:.2f} s "
          f"({100 * (1 - back.valid.mean()):.1f} % cells below the horizon)")
    if args.merl:
        for file in args.merl:
            report_fit(Path(file).stem, read_merl(file), args, None)
        return
    for name, (params, k_b_rgb) in MATERIALS.items():
        table = MerlTable.from_brdf(fmbrdf_merl_table(params, k_b_rgb=k_b_rgb))
        report_fit(name, table, args, params)


if __name__ == "__main__":
    main()
