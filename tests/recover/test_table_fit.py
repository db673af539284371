"""Fitting the FMBRDF's intensity to a tabulated (MERL-layout) BRDF (polarshape.recover.table_fit)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from polarshape.brdf import FMBRDFParams
from polarshape.brdf.tabulate import MERL_SHAPE, fmbrdf_brdf_basis
from polarshape.io.material import load_material, write_material
from polarshape.io.merl import MerlTable, write_merl
from polarshape.recover.table_fit import fit_fmbrdf_to_table, fit_material_table, log_rmse, table_samples

TRUTH = FMBRDFParams(ior=1.6, alpha=0.2, beta=1.5, kappa=0.0, k_s=0.8, k_b=0.3)
K_B_RGB = np.array([0.4, 0.3, 0.1])


@pytest.fixture(scope="module")
def truth_table(sparse_merl_table: Callable[..., np.ndarray]) -> np.ndarray:
    return sparse_merl_table(TRUTH, K_B_RGB)


def test_log_rmse_is_zero_at_the_truth_and_larger_for_another_material(truth_table: np.ndarray) -> None:
    s = table_samples(truth_table, n_samples=None)
    assert s.values.shape[0] == 3 and 1000 < s.cos_i.size <= 3000 and (s.cos_i > 0).all()

    def model(p: FMBRDFParams, k_b: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            f_s, f_b, _ = fmbrdf_brdf_basis(s.light, s.view, p.build_tables())
        return p.k_s * f_s.numpy() + k_b[:, None] * f_b.numpy()

    assert log_rmse(s.values, model(TRUTH, K_B_RGB), s.cos_i) < 1e-12
    wrong = FMBRDFParams(ior=1.4, alpha=0.35, beta=2.0, kappa=0.0, k_s=0.8, k_b=0.3)
    assert log_rmse(s.values, model(wrong, K_B_RGB), s.cos_i) > 0.02


@pytest.mark.slow
def test_rendered_table_refits_to_its_own_parameters(truth_table: np.ndarray) -> None:
    start = FMBRDFParams(ior=1.4, alpha=0.3, beta=2.0, kappa=0.0, k_s=0.5, k_b=0.5)
    fit = fit_fmbrdf_to_table(MerlTable.from_brdf(truth_table), init=start, n_samples=1500, rounds=1, max_nfev=40)
    assert fit.log_rmse < 1e-4 < fit.log_rmse_init
    assert fit.params.ior == pytest.approx(TRUTH.ior, abs=0.03)
    assert fit.params.alpha == pytest.approx(TRUTH.alpha, rel=0.1)
    assert np.allclose(fit.k_s_rgb, TRUTH.k_s, rtol=0.1) and np.allclose(fit.k_b_rgb, K_B_RGB, rtol=0.1)
    assert fit.n_samples == 1500 and fit.fitted == ("ior", "alpha", "beta", "k_s", "k_b")


def test_material_file_from_a_merl_file(tmp_path: Path, truth_table: np.ndarray) -> None:
    path = write_merl(tmp_path / "truth.binary", MerlTable.from_brdf(truth_table))
    material, report = fit_material_table(path, channels="mono", n_samples=800, rounds=1, max_nfev=25)
    assert material.model == "fmbrdf" and material.source["merl"] == str(path)
    assert report["log_rmse"] < report["log_rmse_init"] and report["channels"] == "mono"
    assert material.fmbrdf_params().alpha == pytest.approx(TRUTH.alpha, rel=0.2)
    back = load_material(write_material(tmp_path / "material.json", material))
    assert back.parameters == material.parameters and back.fit["log_rmse"] == report["log_rmse"]


def test_an_empty_table_is_refused() -> None:
    with pytest.raises(ValueError, match="no valid sample"):
        table_samples(np.full((3, *MERL_SHAPE), -1.0))
    with pytest.raises(ValueError, match="shape"):
        table_samples(np.zeros((3, 90, 90)))
