"""``camera.exposures_us`` in scene files: HDR brackets of the simulated camera."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from polarshape.scene.config import parse_scene_config

SPHERE = Path(__file__).resolve().parents[2] / "configs" / "scenes" / "sphere.yaml"


def _scene(**camera: object) -> dict:
    d = yaml.safe_load(SPHERE.read_text())
    d["camera"].pop("exposure_us")
    d["camera"].update(camera)
    return d


def test_the_first_exposure_is_the_reference() -> None:
    config = parse_scene_config(_scene(exposures_us=[8000, 1000]))
    assert config.camera.reference_exposure_us == 8000 and config.camera.exposures_us == (8000.0, 1000.0)
    assert parse_scene_config(_scene()).camera.reference_exposure_us == 10000  # the default exposure_us


@pytest.mark.parametrize("camera,fragment", [
    ({"exposures_us": [8000, 8000]}, "must not repeat an exposure time"),
    ({"exposures_us": [8000, 0]}, "must be positive exposure times"),
    ({"exposures_us": []}, "at least 1 item"),
    ({"exposures_us": [8000, 1000], "exposure_us": 1000}, "differs from the first of camera.exposures_us"),
])
def test_bad_brackets_name_the_field(camera: dict, fragment: str) -> None:
    with pytest.raises(ValueError, match="camera") as err:
        parse_scene_config(_scene(**camera))
    assert fragment in str(err.value)
