"""material.json: written and read back exactly, and every invalid file refused with the key named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from polarshape.brdf.params import FMBRDFParams
from polarshape.errors import OutputExistsError
from polarshape.io.material import MATERIAL_FORMAT, MaterialError, MaterialFile, load_material, write_material


def test_fmbrdf_material_round_trip(tmp_path: Path) -> None:
    params = FMBRDFParams(ior=1.52, alpha=0.24, beta=2.0, kappa=3.5, k_s=0.91, k_b=0.47)
    material = MaterialFile.from_fmbrdf(params, fit={"residual_rms": 0.003}, source={"capture": tmp_path})
    path = write_material(tmp_path / "material.json", material)
    back = load_material(path)
    assert back == material and back.fmbrdf_params() == params
    assert json.loads(path.read_text())["format"] == MATERIAL_FORMAT
    assert back.units["alpha"].startswith("rad") and back.source["capture"] == str(tmp_path)
    with pytest.raises(OutputExistsError):
        write_material(path, material)
    write_material(path, material, overwrite=True)


def test_a_baseline_material_is_not_an_fmbrdf(tmp_path: Path) -> None:
    material = MaterialFile(model="lambertian", parameters={"k_d": 0.6})
    back = load_material(write_material(tmp_path / "m.json", material))
    assert back.parameters == {"k_d": 0.6}
    with pytest.raises(MaterialError, match="'lambertian' is not 'fmbrdf'"):
        back.fmbrdf_params()


GOOD = {"format": MATERIAL_FORMAT, "model": "fmbrdf",
        "parameters": {"ior": 1.5, "alpha": 0.3, "beta": 2.0, "kappa": 0.0, "k_s": 1.0, "k_b": 0.5}}


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(format="other/1"), "format must be 'polarshape-material/1'"),
    (lambda d: d["parameters"].pop("kappa"), r"missing \['kappa'\]"),
    (lambda d: d["parameters"].update(k_d=1.0), r"not of this model \['k_d'\]"),
    (lambda d: d["parameters"].update(ior=7.0), "ior"),
    (lambda d: d.update(model="phong"), "model"),
    (lambda d: d.update(colour="red"), "colour"),
])
def test_invalid_materials_name_the_key(tmp_path: Path, edit, match: str) -> None:  # noqa: ANN001
    data = json.loads(json.dumps(GOOD))
    edit(data)
    path = tmp_path / "m.json"
    path.write_text(json.dumps(data))
    with pytest.raises(MaterialError, match=match):
        load_material(path)


def test_unreadable_material_files(tmp_path: Path) -> None:
    with pytest.raises(MaterialError, match="cannot read"):
        load_material(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(MaterialError, match="not valid JSON"):
        load_material(tmp_path / "bad.json")
    (tmp_path / "twice.json").write_text('{"model": "fmbrdf", "model": "baek"}')
    with pytest.raises(MaterialError, match="'model' appears twice"):
        load_material(tmp_path / "twice.json")
    (tmp_path / "nan.json").write_text(json.dumps(GOOD).replace('"alpha": 0.3', '"alpha": NaN'))
    with pytest.raises(MaterialError, match="alpha"):
        load_material(tmp_path / "nan.json")
