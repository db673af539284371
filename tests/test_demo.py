"""`polarshape demo`: the demo sphere's renders and the files written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from polarshape.demo import demo_material, render_demo, run_demo


def test_render_demo_shapes_and_ranges() -> None:
    r = render_demo(16)
    assert r["stokes"].shape == (16, 16, 3) and r["mosaic"].shape == (32, 32)
    assert r["dolp"].shape == r["aolp"].shape == r["mask"].shape == (16, 16)
    inside = r["mask"]
    assert np.all(r["stokes"][inside, 0] >= 0) and np.all(np.isfinite(r["dolp"]))
    assert np.all(np.abs(r["aolp"]) <= np.pi / 2) and np.all(r["dolp"][~inside] == 0)


def test_run_demo_writes_the_material(tmp_path: Path) -> None:
    summary = run_demo(tmp_path / "demo", size=16)
    written = json.loads((tmp_path / "demo" / "demo.json").read_text())
    assert written["material"] == demo_material().as_kwargs() == summary["material"]
    assert written["material"] == {"ior": 1.5, "alpha": 0.25, "beta": 2.0, "kappa": 20.0, "k_s": 1.0, "k_b": 0.6}
    for name in ("intensity.png", "dolp.png", "aolp.png", "mosaic.png", "stokes.npy"):
        assert (tmp_path / "demo" / name).is_file()
