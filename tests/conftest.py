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
def require_ray() -> object:
    """The ``ray`` module; skip the test when Ray is not installed — unless POLARSHAPE_REQUIRE_RAY=1
    (set by CI, which installs the 'cluster' extra), where that is a failure."""
    try:
        import ray
    except ImportError as exc:
        if os.environ.get("POLARSHAPE_REQUIRE_RAY") == "1":
            pytest.fail(f"POLARSHAPE_REQUIRE_RAY=1 but Ray is not installed: {exc}")
        pytest.skip(f"Ray not installed (pip install -e '.[cluster]'): {exc}")
    return ray


@pytest.fixture(scope="session")
def render_sphere() -> Callable[..., Path]:
    """Render the shipped sphere scene (configs/scenes/sphere.yaml) into a capture folder:
    ``render_sphere(folder, width=, pixel_size_m=, lights=, seed=, material=None, edit=None) -> folder / "capture"``
    (``width`` × ``width`` raw pixels, its first ``lights`` lights, the sphere's material replaced by
    ``material`` if given, then ``edit(scene)`` applied to the scene dict; the scene file is kept beside it)."""
    from polarshape.acquisition.simulated import SimulatedCamera

    def render(folder: Path, *, width: int, pixel_size_m: float, lights: int, seed: int,
               material: dict | None = None, edit: Callable[[dict], None] | None = None) -> Path:
        scene = yaml.safe_load(SPHERE_SCENE.read_text())
        scene["camera"].update(width=width, height=width, pixel_size_m=pixel_size_m)
        scene["lights"] = scene["lights"][:lights]
        if material is not None:
            scene["objects"][0]["material"] = material
        if edit is not None:
            edit(scene)
        (folder / "scene.yaml").write_text(yaml.safe_dump(scene))
        with SimulatedCamera(folder / "scene.yaml", seed=seed) as camera:
            camera.render_capture(folder / "capture", progress=False)
        return folder / "capture"

    return render


@pytest.fixture(scope="session")
def sparse_merl_table() -> Callable[..., object]:
    """``sparse_merl_table(params, k_b_rgb, n_cells=3000, seed=0)``: (3, 90, 90, 180) MERL-layout BRDF
    values of an FMBRDF (``params``, body albedo per channel ``k_b_rgb``) at ``n_cells`` random
    cells, the rest missing (−1): a table that renders and fits in seconds."""
    import numpy as np
    import torch

    from polarshape.brdf.tabulate import MERL_SHAPE, fmbrdf_brdf_basis, merl_directions

    def table(params, k_b_rgb, n_cells: int = 3000, seed: int = 0):  # noqa: ANN001, ANN202
        rng = np.random.default_rng(seed)
        flat = rng.choice(int(np.prod(MERL_SHAPE)), size=n_cells, replace=False)
        idx = np.unravel_index(flat, MERL_SHAPE)
        light, view = merl_directions(*idx)
        with torch.no_grad():
            f_s, f_b, valid = fmbrdf_brdf_basis(torch.from_numpy(light), torch.from_numpy(view), params.build_tables())
        values = np.full((3, *MERL_SHAPE), -1.0)
        f = params.k_s * f_s.numpy() + np.asarray(k_b_rgb, dtype=np.float64)[:, None] * f_b.numpy()
        values[(slice(None), *idx)] = np.where(valid.numpy(), f, -1.0)
        return values

    return table
