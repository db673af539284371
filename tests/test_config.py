"""Run configuration: defaults, path resolution, and every kind of invalid file fails with the key path."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from polarshape.config import RUN_FORMAT, ConfigError, RunConfig, load_run_config, parse_run_config

REPO = Path(__file__).resolve().parents[1]
SCENE = REPO / "configs" / "scenes" / "sphere.yaml"


def _minimal(**extra: object) -> dict:
    return {"input": {"type": "simulated", "scene": str(SCENE)}, **extra}


def _error(data: object, base_dir: Path | None = None) -> str:
    with pytest.raises(ConfigError) as info:
        parse_run_config(data, "run.yaml", base_dir=base_dir)
    return str(info.value)


def test_minimal_config_takes_every_default() -> None:
    config = parse_run_config(_minimal())
    assert config.format == RUN_FORMAT and config.device == "auto" and config.dtype == "float32"
    assert config.recovery.model == "auto" and config.recovery.max_outer_iterations == 20
    assert config.preprocess.mask == "auto" and config.integration.method == "smooth"
    assert config.mesh.poisson is False and config.report.format == "html" and config.output is None


def test_relative_paths_start_at_the_config_folder(tmp_path: Path) -> None:
    (tmp_path / "scenes").mkdir()
    (tmp_path / "scenes" / "s.yaml").write_text("x: 1\n")
    (tmp_path / "cap").mkdir()
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump({"input": {"type": "simulated", "scene": "scenes/s.yaml"}, "output": "res/a"}))
    config = load_run_config(path)
    assert Path(config.input.scene) == (tmp_path / "scenes" / "s.yaml").resolve()
    assert Path(config.output) == (tmp_path / "res" / "a").resolve()
    path.write_text(yaml.safe_dump({"input": {"type": "capture", "path": "cap"}}))
    assert Path(load_run_config(path).input.path) == (tmp_path / "cap").resolve()


def test_shipped_configs_validate() -> None:
    default = load_run_config(REPO / "configs" / "default.yaml")
    assert default.input.type == "simulated" and Path(default.input.scene) == SCENE.resolve()
    assert default.mesh.poisson and default.report.enabled and default.recovery.model == "fmbrdf"
    # the template's only problem is its placeholder capture folder
    with pytest.raises(ConfigError) as info:
        load_run_config(REPO / "configs" / "real_capture_template.yaml")
    message = str(info.value)
    assert "1 problem(s)" in message and "input.path" in message and "my_object" in message
    for name in ("blob", "two_materials", "nearfield_sphere", "nearfield_blob"):  # the scene examples
        example = load_run_config(REPO / "configs" / f"{name}.yaml")
        assert example.input.type == "simulated" and Path(example.input.scene).is_file()
        assert example.recovery.model == "fmbrdf" and example.recovery.materials == "auto"


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (_minimal(recovery={"modle": "fmbrdf"}), ["recovery.modle: unknown key", "did you mean 'model'", "per_pixel_albedo"]),
        (_minimal(outptu="x"), ["outptu: unknown key", "did you mean 'output'", "allowed keys here"]),
        ({"input": {"type": "simulated", "scene": str(SCENE), "sceen": "x"}}, ["input.sceen: unknown key"]),
        (_minimal(mesh={"poisson": True, "octree": 8}), ["mesh.octree: unknown key", "poisson_depth"]),
    ],
)
def test_unknown_keys(data: dict, expected: list[str]) -> None:
    message = _error(data)
    for part in expected:
        assert part in message


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (_minimal(recovery={"max_outer_iterations": "20"}), ["recovery.max_outer_iterations", "valid integer", "'20'"]),
        (_minimal(recovery={"max_outer_iterations": 2.5}), ["recovery.max_outer_iterations", "valid integer", "2.5"]),
        (_minimal(mesh={"poisson": 1}), ["mesh.poisson", "valid boolean", "got 1"]),
        (_minimal(preprocess={"mask_threshold": "low"}), ["preprocess.mask_threshold", "valid number"]),
        (_minimal(integration={"pixel_size_m": [1, 2]}), ["integration.pixel_size_m", "valid number"]),
        (_minimal(output=5), ["output", "valid string"]),
        (_minimal(report=True), ["report: must be a mapping", "max_curve_pixels"]),
        ({"input": "captures/x"}, ["input: must be a mapping", "type"]),
    ],
)
def test_wrong_types(data: dict, expected: list[str]) -> None:
    message = _error(data)
    for part in expected:
        assert part in message


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (_minimal(device="gpu"), ["device", "'auto', 'cpu' or 'cuda'", "'gpu'"]),
        (_minimal(dtype="float16"), ["dtype", "'float32' or 'float64'"]),
        (_minimal(recovery={"model": "baek"}), ["recovery.model", "'auto', 'fmbrdf' or 'lambertian'"]),
        (_minimal(integration={"method": "poisson"}), ["integration.method", "'smooth' or 'bilateral'"]),
        (_minimal(report={"format": "pdf"}), ["report.format", "'html' or 'png'"]),
        (_minimal(export={"normal_convention": "directx"}), ["export.normal_convention", "'opencv' or 'opengl'"]),
        (_minimal(format="polarshape-run/2"), ["format", "polarshape-run/1"]),
        (_minimal(preprocess={"sample_at": "middle"}), ["preprocess.sample_at", "'centre'", "'top_left'"]),
        (_minimal(preprocess={"demosaic": "superpixel", "sample_at": "top_left"}),
         ["preprocess", "sample_at 'top_left' needs preprocess.demosaic 'bilinear'"]),
        ({"input": {"type": "camera", "scene": str(SCENE)}}, ["input.type", "'capture', 'simulated' or 'session'"]),
    ],
)
def test_values_outside_the_allowed_set(data: dict, expected: list[str]) -> None:
    message = _error(data)
    for part in expected:
        assert part in message


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (_minimal(recovery={"max_outer_iterations": 0}), ["recovery.max_outer_iterations", "greater than or equal to 1", "got 0"]),
        (_minimal(recovery={"subsample_pixels": 10}), ["recovery.subsample_pixels", "greater than or equal to 64"]),
        (_minimal(preprocess={"mask_threshold": 1.5}), ["preprocess.mask_threshold", "less than 1", "1.5"]),
        (_minimal(preprocess={"erode_px": -1}), ["preprocess.erode_px", "greater than or equal to 0"]),
        (_minimal(integration={"pixel_size_m": 0}), ["integration.pixel_size_m", "greater than 0"]),
        (_minimal(mesh={"poisson_depth": 20}), ["mesh.poisson_depth", "less than or equal to 12", "20"]),
        (_minimal(seed=-3), ["seed", "greater than or equal to 0"]),
    ],
)
def test_out_of_range_values(data: dict, expected: list[str]) -> None:
    message = _error(data)
    for part in expected:
        assert part in message


def test_several_problems_are_reported_together() -> None:
    message = _error(_minimal(device="gpu", recovery={"modle": 1}, mesh={"poisson_depth": 0}))
    assert "3 problem(s)" in message
    assert message.index("device") < message.index("recovery.modle") < message.index("mesh.poisson_depth")


def test_input_section_rules(tmp_path: Path) -> None:
    assert "input: required key missing" in _error({})
    assert "input.type: required key missing" in _error({"input": {"scene": str(SCENE)}})
    assert "input.path is required when input.type is 'capture'" in _error({"input": {"type": "capture"}})
    assert "input.scene is required" in _error({"input": {"type": "simulated"}})
    assert "input.session is required" in _error({"input": {"type": "session"}})
    message = _error({"input": {"type": "simulated", "scene": str(SCENE), "path": str(tmp_path)}})
    assert "input.path does not apply to input.type 'simulated'" in message
    message = _error({"input": {"type": "capture", "path": str(tmp_path), "seed": 1}})
    assert "input.seed applies to input.type 'simulated' only" in message
    message = _error({"input": {"type": "capture", "path": "nowhere"}}, base_dir=tmp_path)
    assert "is not a capture folder" in message and str(tmp_path / "nowhere") in message
    message = _error({"input": {"type": "simulated", "scene": "missing.yaml"}}, base_dir=tmp_path)
    assert "input.scene" in message and "not found" in message
    assert "must be a non-empty path" in _error({"input": {"type": "simulated", "scene": " "}})


def test_file_level_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="config file not found"):
        load_run_config(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("input: {type: simulated\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_run_config(bad)
    bad.write_text("- just\n- a list\n")
    with pytest.raises(ConfigError, match="must be a YAML mapping"):
        load_run_config(bad)
    bad.write_text("")
    with pytest.raises(ConfigError, match="must be a YAML mapping"):
        load_run_config(bad)
    bad.write_bytes(b"input: \xff\xfe\n")
    with pytest.raises(ConfigError, match="UTF-8"):
        load_run_config(bad)


def test_config_is_frozen_and_round_trips() -> None:
    config = parse_run_config(_minimal(recovery={"model": "lambertian"}))
    with pytest.raises(Exception):
        config.device = "cpu"  # type: ignore[misc]
    again = RunConfig.model_validate(config.model_dump(mode="json"))
    assert again == config

