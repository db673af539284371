"""``polarshape batch --engine ray`` on a local Ray instance started by the test (``ray.init(num_cpus=2)``):
the same worker function as the local engine, one Ray task per capture; a corrupt capture is
recorded and the others still run. Needs the 'cluster' extra (CI: POLARSHAPE_REQUIRE_RAY=1)."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import yaml

from polarshape.batch import LOG_FILE, find_captures, run_batch
from polarshape.cli import main
from polarshape.cli.batch import SOME_FAILED
from polarshape.config import load_batch_config
from polarshape.io.results import is_result_folder

CONFIG = {
    "progress": False, "recovery": {"model": "fmbrdf", "max_outer_iterations": 2}, "validation": {"holdout": "none"},
    "mesh": {"poisson": False, "obj": False}, "report": {"enabled": False}, "export": {"exr": False},
}


@pytest.fixture(scope="module")
def ray_instance(require_ray: object) -> Iterator[object]:
    """One local Ray instance for the module (it takes seconds to start)."""
    ray = require_ray
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)  # type: ignore[attr-defined]
    try:
        yield ray
    finally:
        ray.shutdown()  # type: ignore[attr-defined]


@pytest.fixture(scope="module")
def batch(tmp_path_factory: pytest.TempPathFactory, render_sphere: Callable[..., Path]) -> tuple[Path, Path]:
    """(captures folder with c0, c1, c2 and a corrupt 'bad', batch config)."""
    folder = tmp_path_factory.mktemp("ray_batch")
    capture = render_sphere(folder, width=32, pixel_size_m=4.0e-4, lights=6, seed=2)
    caps = folder / "caps"
    for name in ("c0", "c1", "c2", "bad"):
        shutil.copytree(capture, caps / name)
    (caps / "bad" / "capture.yaml").write_text("format: [unclosed\n")
    config = folder / "batch.yaml"
    config.write_text(yaml.safe_dump(CONFIG))
    return caps, config


def test_ray_engine_runs_every_capture_and_records_the_corrupt_one(
        ray_instance: object, batch: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    caps, config = batch
    out = tmp_path / "out"
    result = run_batch(load_batch_config(config), find_captures([str(caps / "*")]), out, engine="ray",
                       config_path=config, progress=False)
    assert result.engine == "ray" and result.failed == 1 and result.count("done") == 3
    by_name = {o.name: o for o in result.outcomes}
    assert by_name["bad"].error["type"] == "CaptureError" and not (out / "bad").exists()
    for name in ("c0", "c1", "c2"):
        assert is_result_folder(out / name) and "stage recovery" in (out / name / LOG_FILE).read_text()
        assert not by_name[name].worker.endswith(f":{os.getpid()}")  # run by a Ray worker, not here
    failed = json.loads((out / "failed.json").read_text())["failed"]
    assert [f["capture"] for f in failed] == ["bad"]

    # resume on Ray too, from the command line (the Ray instance already initialised is used): only the
    # failed capture is run again, and it fails again (exit status 4)
    mtimes = {n: (out / n / "params.json").stat().st_mtime_ns for n in ("c0", "c1", "c2")}
    assert main(["batch", str(config), str(caps / "*"), "--out", str(out), "--engine", "ray", "-q"]) == SOME_FAILED
    assert {n: (out / n / "params.json").stat().st_mtime_ns for n in mtimes} == mtimes
    assert "3 complete from an earlier run (skipped); 1 failed" in capsys.readouterr().out
