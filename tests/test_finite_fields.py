"""Every float of a run configuration, a scene file and a capture.yaml must be finite: ``.inf`` or
``.nan`` is a validation error naming the key path (it used to pass and fail much later)."""

from __future__ import annotations

import copy
import math
import types
import typing
from pathlib import Path
from typing import Any

import pytest
import yaml
from pydantic import BaseModel

from polarshape.cli import main
from polarshape.config import ConfigError, RunConfig, parse_run_config
from polarshape.errors import CaptureError
from polarshape.io.capture import parse_capture_spec
from polarshape.scene.config import parse_scene_config

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO / "configs" / "scenes"
NON_FINITE = [math.inf, -math.inf, math.nan]


def _section(annotation: Any) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return next((a for a in typing.get_args(annotation) if _section(a) is not None), None)
    return None


def _float_keys(model: type[BaseModel], prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Key paths of every float field of a config model, sections included."""
    keys = []
    for name, field in model.model_fields.items():
        section = _section(field.annotation)
        if section is not None:
            keys += _float_keys(section, (*prefix, name))
        elif field.annotation is float or float in typing.get_args(field.annotation):
            keys.append((*prefix, name))
    return keys


RUN_FLOATS = _float_keys(RunConfig)


def test_the_run_config_has_the_floats_we_know_of() -> None:
    names = {".".join(k) for k in RUN_FLOATS}
    assert {"initial_normals.noise_std", "integration.pixel_size_m", "preprocess.mask_threshold",
            "recovery.smoothness"} <= names


@pytest.mark.parametrize("value", NON_FINITE, ids=["inf", "-inf", "nan"])
@pytest.mark.parametrize("key", RUN_FLOATS, ids=[".".join(k) for k in RUN_FLOATS])
def test_a_non_finite_run_config_float_is_named(key: tuple[str, ...], value: float, tmp_path: Path) -> None:
    data: dict[str, Any] = {"input": {"type": "capture", "path": str(tmp_path)}}
    section = data
    for part in key[:-1]:
        section = section.setdefault(part, {})
    section[key[-1]] = value
    with pytest.raises(ConfigError) as info:
        parse_run_config(data, "run.yaml")
    message = str(info.value)
    assert "1 problem(s)" in message and f"{'.'.join(key)}: Input should be a finite number; got {value!r}" in message


def test_polarshape_run_refuses_an_infinite_pixel_size(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "cap").mkdir()
    config = tmp_path / "run.yaml"
    config.write_text("input: {type: capture, path: cap}\ninitial_normals: {noise_std: .inf}\n"
                      "integration: {pixel_size_m: .nan}\n")
    assert main(["run", str(config), "--out", str(tmp_path / "res")]) == 2
    err = capsys.readouterr().err
    assert "2 problem(s)" in err and "initial_normals.noise_std" in err and "integration.pixel_size_m" in err
    assert not (tmp_path / "res").exists()


def _numeric_leaves(data: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    if isinstance(data, dict):
        return [p for k, v in data.items() for p in _numeric_leaves(v, (*path, k))]
    if isinstance(data, list):
        return [p for i, v in enumerate(data) for p in _numeric_leaves(v, (*path, i))]
    return [path] if isinstance(data, (int, float)) and not isinstance(data, bool) else []


def _replaced(data: Any, path: tuple[Any, ...], value: Any) -> Any:
    out = copy.deepcopy(data)
    target = out
    for part in path[:-1]:
        target = target[part]
    target[path[-1]] = value
    return out


#: Every kind of scene entry: the shipped scenes, plus the optional floats they leave out.
SCENE_FILES = {name: yaml.safe_load((SCENES / f"{name}.yaml").read_text()) for name in ("sphere", "blob", "textured")}
SCENE_FILES["extras"] = {
    "camera": {"projection": "orthographic", "width": 16, "height": 16, "pixel_size_m": 1e-3, "principal_point": [7.5, 7.5]},
    "sensor": {"e_per_count_12bit": 2.5},
    "objects": [{"shape": {"type": "torus", "center": [0, 0, 1], "major_radius": 0.004, "minor_radius": 0.001},
                 "material": {"model": "baek", "ior": 1.5, "k_s": 1.0, "k_d": 0.5, "alpha": 0.3}},
                {"shape": {"type": "plane", "point": [0, 0, 2], "normal": [0, 0, -1], "size": [0.1, 0.1]},
                 "material": {"model": "lambertian", "k_d": 0.5}}],
    "lights": [{"position": [0.1, 0.0, -0.5], "intensity": 2.0}],
}
SCENE_LEAVES = [(name, path) for name, data in SCENE_FILES.items() for path in _numeric_leaves(data)]


@pytest.mark.parametrize("value", [math.inf, math.nan], ids=["inf", "nan"])
@pytest.mark.parametrize(("scene", "path"), SCENE_LEAVES, ids=[f"{n}:{'.'.join(map(str, p))}" for n, p in SCENE_LEAVES])
def test_a_non_finite_scene_number_is_named(scene: str, path: tuple[Any, ...], value: float) -> None:
    with pytest.raises(ValueError) as info:
        parse_scene_config(_replaced(SCENE_FILES[scene], path, value), base_dir=SCENES)
    message = str(info.value)
    assert "finite" in message and str(path[-1]) in message, message


CAPTURE = {
    "format": "polarshape-capture/1",
    "camera": {"projection": "perspective", "bit_depth": 12, "black_level": 0.0,
               "intrinsics": {"fx": 100.0, "fy": 100.0, "cx": 7.5, "cy": 7.5},
               "mosaic": {"layout": [[90.0, 45.0], [135.0, 0.0]]}},
    "lights": [{"direction": [0.0, 0.0, -1.0], "intensity": 1.0, "frame": "frames/000.png"},
               {"position": [0.1, 0.0, -0.5], "intensity": 1.0, "frame": "frames/001.png"}],
}


def test_the_capture_example_is_valid() -> None:
    assert len(parse_capture_spec(CAPTURE).lights) == 2


@pytest.mark.parametrize("path", _numeric_leaves(CAPTURE), ids=lambda p: ".".join(map(str, p)))
def test_a_non_finite_capture_number_is_named(path: tuple[Any, ...]) -> None:
    with pytest.raises(CaptureError) as info:
        parse_capture_spec(_replaced(CAPTURE, path, math.inf))
    message = str(info.value)
    assert "finite" in message and str(path[-1]) in message, message
