"""Fixtures shared by the whole test suite."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml

SPHERE_SCENE = Path(__file__).resolve().parents[1] / "configs" / "scenes" / "sphere.yaml"


@pytest.fixture
def require_aravis() -> None:
    """Skip a test when Aravis/PyGObject cannot be used — unless POLARSHAPE_REQUIRE_ARAVIS=1
    (set by CI, which installs them), where that is a failure."""
    from polarshape.acquisition.aravis import import_aravis
    from polarshape.acquisition.camera import CameraError

    try:
        import_aravis()
    except CameraError as exc:
        if os.environ.get("POLARSHAPE_REQUIRE_ARAVIS") == "1":
            pytest.fail(f"POLARSHAPE_REQUIRE_ARAVIS=1 but Aravis is unusable: {exc}")
        pytest.skip(f"Aravis/PyGObject not installed: {exc}")


@pytest.fixture(scope="session")
def render_sphere() -> Callable[..., Path]:
    """Render the shipped sphere scene (configs/scenes/sphere.yaml) into a capture folder:
    ``render_sphere(folder, width=, pixel_size_m=, lights=, seed=) -> folder / "capture"``
    (``width`` × ``width`` raw pixels, its first ``lights`` lights; the scene file is kept beside it)."""
    from polarshape.acquisition.simulated import SimulatedCamera

    def render(folder: Path, *, width: int, pixel_size_m: float, lights: int, seed: int) -> Path:
        scene = yaml.safe_load(SPHERE_SCENE.read_text())
        scene["camera"].update(width=width, height=width, pixel_size_m=pixel_size_m)
        scene["lights"] = scene["lights"][:lights]
        (folder / "scene.yaml").write_text(yaml.safe_dump(scene))
        with SimulatedCamera(folder / "scene.yaml", seed=seed) as camera:
            camera.render_capture(folder / "capture", progress=False)
        return folder / "capture"

    return render
