"""``polarshape material``: exit statuses and the one-line result."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from polarshape.cli import main
from polarshape.cli.material import parse_models
from polarshape.errors import ConfigError
from polarshape.io.material import load_material


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory, render_sphere: Callable[..., Path]) -> Path:
    return render_sphere(tmp_path_factory.mktemp("cap"), width=48, pixel_size_m=0.028 / 48, lights=2, seed=3,
                         material={"model": "baek", "ior": 1.6, "k_s": 0.8, "k_d": 0.6, "alpha": 0.2})


def test_material_command(capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "mat"
    assert main(["material", str(capture), "--shape", "sphere", "--models", "baek,lambertian", "--out", str(out)]) == 0
    assert "best model baek" in capsys.readouterr().out
    assert load_material(out / "material.json").model == "baek"
    assert main(["material", str(capture), "--shape", "sphere", "--models", "baek", "--out", str(out)]) == 1
    assert "already exists" in capsys.readouterr().err
    assert main(["material", str(capture), "--shape", "sphere", "--models", "baek", "--frames", "1",
                 "--out", str(out), "--overwrite"]) == 0
    assert load_material(out / "material.json").source["frames"] == [1]


@pytest.mark.parametrize("args, status, message", [
    (["--shape", "mesh.ply"], 2, "no such file"),
    ([], 2, "give --shape"),
    (["--shape", "sphere", "--models", "phong"], 2, "unknown reflectance model"),
    (["--shape", "sphere", "--frames", "5"], 2, "distinct frame indices"),
    (["--shape", "nowhere.npy"], 2, "no such file"),
])
def test_material_command_refusals(capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                   args: list[str], status: int, message: str) -> None:
    assert main(["material", str(capture), *args, "--out", str(tmp_path / "o")]) == status
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_material_command_refuses_the_capture_as_output(capture: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["material", str(capture), "--shape", "sphere", "--models", "baek", "--out", str(capture),
                 "--overwrite"]) == 1
    assert "input" in capsys.readouterr().err


def test_parse_models() -> None:
    assert parse_models("fmbrdf, baek,") == ("fmbrdf", "baek")
    with pytest.raises(ConfigError):
        parse_models(" , ")


@pytest.mark.slow
def test_material_from_a_brdf_table(tmp_path: Path, capsys: pytest.CaptureFixture[str], sparse_merl_table) -> None:  # noqa: ANN001
    """``--brdf-table``: a MERL file of an FMBRDF gives a material.json holding its parameters."""
    from polarshape.brdf import FMBRDFParams
    from polarshape.io.merl import MerlTable, write_merl

    truth = FMBRDFParams(ior=1.6, alpha=0.2, beta=1.5, kappa=0.0, k_s=0.8, k_b=0.3)
    table = write_merl(tmp_path / "plastic.binary", MerlTable.from_brdf(sparse_merl_table(truth, (0.3, 0.3, 0.3))))
    assert main(["material", "--brdf-table", str(table), "--out", str(tmp_path / "m")]) == 0
    assert "log-RMSE" in capsys.readouterr().out
    material = load_material(tmp_path / "m" / "material.json")
    assert material.model == "fmbrdf" and material.source["merl"] == str(table)
    assert material.parameters["ior"] == pytest.approx(1.6, abs=0.03)
    assert material.parameters["alpha"] == pytest.approx(0.2, rel=0.1)
    assert material.fit["log_rmse"] < 1e-3
    assert main(["material", "--brdf-table", str(table), "--out", str(tmp_path / "m")]) == 1  # exists


def test_material_table_refusals(tmp_path: Path, capture: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "bad.binary").write_bytes(b"\x00" * 10)
    assert main(["material", "--brdf-table", str(tmp_path / "bad.binary"), "--out", str(tmp_path / "o")]) == 2
    assert "bad.binary" in capsys.readouterr().err and not (tmp_path / "o").exists()
    assert main(["material", str(capture), "--brdf-table", str(tmp_path / "bad.binary")]) == 2
    assert "not both" in capsys.readouterr().err
    assert main(["material"]) == 2
    assert "give a CAPTURE" in capsys.readouterr().err
    (tmp_path / "table_dir").mkdir()
    table = tmp_path / "table_dir" / "t.binary"
    table.write_bytes(b"\x00" * 10)
    assert main(["material", "--brdf-table", str(table), "--out", str(tmp_path / "table_dir"), "--overwrite"]) == 1
    assert "it is or holds the input" in capsys.readouterr().err and table.exists()
