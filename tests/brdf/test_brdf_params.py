"""The one FMBRDF parameter type: defaults, the params.json dict, checks, and who is one."""

from __future__ import annotations

import math

import pytest

from polarshape.brdf import FMBRDF_PARAM_NAMES, PARAM_BOUNDS, FMBRDFParams
from polarshape.scene.config import FMBRDFConfig
from polarshape.scene.materials import FMBRDFMaterial


def test_defaults_and_the_params_json_dict() -> None:
    p = FMBRDFParams()
    assert p.as_dict() == {"ior": 1.5, "alpha": 0.3, "beta": 2.0, "kappa": 0.0, "k_s": 1.0, "k_b": 0.5, "r_k": 0.5}
    assert list(p.as_dict()) == [*FMBRDF_PARAM_NAMES, "r_k"]
    assert set(FMBRDF_PARAM_NAMES) == set(PARAM_BOUNDS)
    assert FMBRDFParams(k_s=0.0).as_dict()["r_k"] == math.inf
    assert p.as_kwargs() == {k: v for k, v in p.as_dict().items() if k != "r_k"}


def test_copy_with_a_change_and_no_check_on_construction() -> None:
    p = FMBRDFParams(ior=1.4, alpha=0.2)
    q = FMBRDFParams(**{**vars(p), "kappa": 20.0})
    assert (q.ior, q.alpha, q.kappa, p.kappa) == (1.4, 0.2, 20.0, 0.0)
    FMBRDFParams(alpha=-1.0)  # a fit may pass through any value; validate() is explicit


@pytest.mark.parametrize("name,value", [("alpha", 0.0), ("ior", 0.9), ("beta", math.nan), ("k_b", -0.1)])
def test_validate_names_the_parameter(name: str, value: float) -> None:
    with pytest.raises(ValueError, match=name):
        FMBRDFParams(**{name: value}).validate()


def test_material_and_scene_entry_are_the_same_type() -> None:
    material = FMBRDFMaterial(ior=1.6, k_b=0.4)
    entry = FMBRDFConfig(ior=1.6, k_b=0.4)
    assert isinstance(material, FMBRDFParams) and isinstance(entry, FMBRDFParams)
    assert material.as_dict() == entry.as_dict() == FMBRDFParams(ior=1.6, k_b=0.4).as_dict()
    assert entry.to_material().as_kwargs() == material.as_kwargs()
