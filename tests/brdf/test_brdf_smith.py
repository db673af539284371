import math

import numpy as np
import pytest
import scipy.integrate as si
import torch

from polarshape.brdf.distribution import d_normalisation
from polarshape.brdf.smith import build_smith_table, clipped_cos_azimuthal, projected_area_exact

CASES = [(0.01, 2.0), (0.01, 0.5), (0.01, 4.0), (0.3, 2.0), (2.0, 4.0), (1.0, 0.5), (0.1, 1.0)]


def _params(a, b):
    A = torch.tensor(a, dtype=torch.float64)
    B = torch.tensor(b, dtype=torch.float64)
    return A, B, d_normalisation(A, B)


def test_clipped_cos_azimuthal_against_numeric():
    for a, b in [(0.3, 0.1), (0.3, 0.5), (0.0, 0.7), (0.2, 0.2)]:
        num, _ = si.quad(lambda p: max(0.0, a + b * math.cos(p)), 0, 2 * math.pi, limit=200, points=[math.pi / 2, math.pi])
        got = float(clipped_cos_azimuthal(torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64)))
        assert got == pytest.approx(num, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("a,b", CASES)
def test_smith_limits(a, b):
    A, B, c = _params(a, b)
    th = torch.tensor([0.0, 0.7, math.pi / 2], dtype=torch.float64)
    p = projected_area_exact(th, A, B, c)
    assert float(p[0]) == pytest.approx(1.0, abs=1e-6)  # G1(normal view) = 1: eq. 5
    assert float(p[1]) >= math.cos(0.7) - 1e-9  # P ≥ cos θ, i.e. Λ ≥ 0
    assert float(p[2]) > 0  # finite G1 at grazing


@pytest.mark.parametrize("a,b", [(0.05, 2.0), (0.3, 1.0), (0.8, 3.0)])
def test_smith_identity_visible_normals(a, b):
    """∫ G1(ω) [ω·m]₊ D(m) dω_m = cos θ_ω (Heitz 2014, eq. 17), with the 2-D integral by scipy."""
    A, B, c = _params(a, b)
    tab = build_smith_table(A, B, c)
    cval = float(c)
    for tw in (0.3, 1.0, 1.45):
        g1 = float(tab.g1(torch.tensor(tw, dtype=torch.float64)))

        def integrand(phi, th):
            cosm = math.cos(tw) * math.cos(th) + math.sin(tw) * math.sin(th) * math.cos(phi)
            return max(0.0, cosm) * cval * math.exp(-((th / a) ** b)) * math.sin(th)

        val, _ = si.dblquad(integrand, 0, math.pi / 2, 0, 2 * math.pi, epsabs=1e-10, epsrel=1e-8)
        assert g1 * val == pytest.approx(math.cos(tw), rel=2e-3)


@pytest.mark.parametrize("a,b", CASES)
def test_table_against_exact(a, b):
    A, B, c = _params(a, b)
    tab = build_smith_table(A, B, c)
    th = torch.tensor(np.concatenate([np.linspace(0, math.pi / 2, 40), math.pi / 2 - np.geomspace(1e-5, 0.5, 40)]))
    ex = projected_area_exact(th, A, B, c)
    rel = ((tab.projected_area(th) - ex) / ex).abs().max()
    assert float(rel) < 5e-4
