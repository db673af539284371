"""Materials: they call the forward models with the albedo scaled per point."""

from __future__ import annotations

import math

import pytest
import torch

from polarshape.brdf.baselines import baek_pbrdf_stokes, lambertian_stokes
from polarshape.brdf.fmbrdf import fmbrdf_stokes
from polarshape.scene.materials import BaekMaterial, FMBRDFMaterial, LambertianMaterial, Material

F64 = torch.float64


def _vectors(n: int = 64):
    g = torch.Generator().manual_seed(0)
    jitter = torch.randn(n, 3, generator=g, dtype=F64) * 0.4
    normal = torch.nn.functional.normalize(jitter + torch.tensor([0, 0, -1.0], dtype=F64), dim=-1)
    light = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, -1.0], dtype=F64), dim=0).expand(n, 3)
    view = torch.tensor([0.0, 0.0, -1.0], dtype=F64).expand(n, 3)
    scale = torch.rand(n, generator=g, dtype=F64) + 0.2
    return normal, light, view, scale


def test_fmbrdf_material_scales_k_b_and_caches_its_tables():
    n, l, v, scale = _vectors()
    mat = FMBRDFMaterial(ior=1.5, k_s=0.7, k_b=0.4, alpha=0.3, beta=2.0, kappa=5.0)
    assert isinstance(mat, Material)
    got = mat.stokes(n, l, v, scale)
    tables = mat.tables_on("cpu")
    assert mat.stokes(n, l, v, scale) is not got and mat.tables_on("cpu") is tables  # built once
    expect = fmbrdf_stokes(n, l, v, ior=1.5, k_s=0.7, k_b=0.4 * scale, alpha=0.3, beta=2.0, kappa=5.0, tables=tables)
    assert torch.allclose(got, expect, rtol=1e-12, atol=1e-15)
    # a larger albedo scale raises s0 where the body term is present
    brighter = mat.stokes(n, l, v, scale * 2)
    assert torch.all(brighter[:, 0] >= got[:, 0]) and torch.any(brighter[:, 0] > got[:, 0])


def test_fmbrdf_material_checks_its_parameters():
    with pytest.raises(ValueError, match="alpha"):
        FMBRDFMaterial(alpha=0.0)


def test_lambertian_and_baek_materials():
    n, l, v, scale = _vectors()
    assert torch.allclose(LambertianMaterial(0.6).stokes(n, l, v, scale), lambertian_stokes(n, l, v, k_d=0.6 * scale))
    cos = (n * l).sum(-1)
    assert torch.allclose(LambertianMaterial(0.6).stokes(n, l, v, scale)[:, 0], 0.6 * scale * cos.clamp_min(0) / math.pi)
    baek = BaekMaterial(ior=1.4, k_s=0.5, k_d=0.3, alpha=0.2, distribution="beckmann")
    expect = baek_pbrdf_stokes(n, l, v, ior=1.4, k_s=0.5, k_d=0.3 * scale, alpha=0.2, distribution="beckmann")
    assert torch.allclose(baek.stokes(n, l, v, scale), expect)
    with pytest.raises(ValueError, match="distribution"):
        BaekMaterial(distribution="phong")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="k_d"):
        LambertianMaterial(-1.0)
