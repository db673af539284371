"""docs/capture-format.md keeps up with the code: every field of capture.yaml is named, every allowed
value of the closed fields is listed, and the example capture.yaml is valid."""

from __future__ import annotations

import re
import typing
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel

from polarshape.io.capture import CaptureSpec, parse_capture_spec
from polarshape.io.results import RESULT_FORMAT

DOC = Path(__file__).resolve().parents[1] / "docs" / "capture-format.md"


def _text() -> str:
    return DOC.read_text(encoding="utf-8")


def _models(model: type[BaseModel]) -> list[type[BaseModel]]:
    """``model`` and every pydantic model its fields hold (through Optional, tuples, …)."""
    found: list[type[BaseModel]] = []

    def visit(annotation: object) -> None:
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            if annotation not in found:
                found.append(annotation)
                for info in annotation.model_fields.values():
                    visit(info.annotation)
        for arg in typing.get_args(annotation):
            visit(arg)

    visit(model)
    return found


def _literal_values(annotation: object) -> list[str]:
    if typing.get_origin(annotation) is typing.Literal:
        return [str(v) for v in typing.get_args(annotation)]
    return [v for arg in typing.get_args(annotation) for v in _literal_values(arg)]


def test_the_walk_finds_every_model() -> None:
    names = {m.__name__ for m in _models(CaptureSpec)}
    assert {"CaptureSpec", "CameraSpec", "IntrinsicsSpec", "MosaicSpec", "CaptureLightSpec"} <= names


@pytest.mark.parametrize("model", _models(CaptureSpec), ids=lambda m: m.__name__)
def test_every_field_and_model_is_named(model: type[BaseModel]) -> None:
    text = _text()
    assert f"`{model.__name__}`" in text
    missing = [name for name in model.model_fields if f"`{name}`" not in text]
    assert not missing, f"docs/capture-format.md does not name {model.__name__} fields {missing}"


@pytest.mark.parametrize("model", _models(CaptureSpec), ids=lambda m: m.__name__)
def test_every_allowed_value_is_listed(model: type[BaseModel]) -> None:
    text = _text()
    for name, info in model.model_fields.items():
        for value in _literal_values(info.annotation):
            assert f"`{value}`" in text, f"{model.__name__}.{name}: value {value!r} is not in docs/capture-format.md"


def test_the_example_capture_yaml_is_valid() -> None:
    blocks = re.findall(r"```yaml\n(.*?)```", _text(), flags=re.S)
    example = next(b for b in blocks if "format: polarshape-capture/1" in b)
    spec = parse_capture_spec(yaml.safe_load(example), "docs/capture-format.md")
    assert spec.camera.projection == "perspective" and len(spec.lights) == 2
    assert spec.lights[1].position is not None  # both kinds of light are shown


def test_the_result_format_tag_is_the_code_s() -> None:
    assert f"`format: {RESULT_FORMAT}`" in _text()
