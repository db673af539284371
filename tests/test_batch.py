"""``polarshape batch`` on the local engine: four small simulated captures, one corrupt; the tables,
per-capture logs, exit status, resume (in-process and after a SIGKILL in the middle); and the parts
(capture discovery, pool sizing, summary rows, the batch configuration)."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml

from polarshape.batch import (
    BATCH_FORMAT, FAILED_FORMAT, LOG_FILE, SUMMARY_COLUMNS, find_captures, plan_local, ray_uses_gpus, read_failed,
    summary_row,
)
from polarshape.batch.engines import import_ray
from polarshape.cli import main
from polarshape.cli.batch import SOME_FAILED
from polarshape.config import ConfigError, load_batch_config, parse_batch_config
from polarshape.errors import CaptureError, DeviceError, PipelineError
from polarshape.io.results import is_result_folder

#: A fast run: FMBRDF with 2 outer iterations (so μ and α are fitted), no report, no extras.
BATCH_CONFIG = {
    "progress": False, "recovery": {"model": "fmbrdf", "max_outer_iterations": 2},
    "validation": {"holdout": "none"}, "mesh": {"poisson": False, "obj": False}, "report": {"enabled": False},
    "export": {"exr": False},
}


def make_batch(folder: Path, capture: Path, good: int) -> tuple[Path, Path]:
    """``folder/caps`` with ``good`` copies of ``capture`` (c0, c1, ...) and a corrupt one (``bad``:
    capture.yaml does not parse), and ``folder/batch.yaml``; returns (captures folder, config)."""
    caps = folder / "caps"
    for i in range(good):
        shutil.copytree(capture, caps / f"c{i}")
    shutil.copytree(capture, caps / "bad")
    (caps / "bad" / "capture.yaml").write_text("format: [unclosed\n")
    config = folder / "batch.yaml"
    config.write_text(yaml.safe_dump(BATCH_CONFIG))
    return caps, config


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory, render_sphere: Callable[..., Path]) -> Path:
    """A 32×32-raw-pixel sphere under 6 lights, with ground truth (read-only: tests copy it)."""
    return render_sphere(tmp_path_factory.mktemp("batch"), width=32, pixel_size_m=4.0e-4, lights=6, seed=2)


def _rows(out: Path) -> dict[str, dict[str, str]]:
    with (out / "summary.csv").open(newline="") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames or ()) == SUMMARY_COLUMNS
        return {row["capture"]: row for row in reader}


def _recorded_done(out: Path) -> bool:
    """Some capture has a result folder and summary.csv says it is done (read while a batch writes it:
    the table is replaced atomically, so it is whole or absent)."""
    if not list(out.glob("c*/params.json")) or not (out / "summary.csv").exists():
        return False
    return any(row["status"] == "done" for row in _rows(out).values())


def test_local_batch_runs_every_capture_records_the_corrupt_one_and_resumes(
        tmp_path: Path, capture: Path, capsys: pytest.CaptureFixture[str]) -> None:
    caps, config = make_batch(tmp_path, capture, good=3)
    out = tmp_path / "out"
    status = main(["batch", str(config), str(caps / "*"), "--out", str(out), "--workers", "2", "-q"])
    assert status == SOME_FAILED, capsys.readouterr().err
    assert "3 done" in capsys.readouterr().out

    rows = _rows(out)
    assert sorted(rows) == ["bad", "c0", "c1", "c2"]
    assert rows["bad"]["status"] == "failed" and rows["bad"]["error"].startswith("CaptureError: ")
    assert "capture.yaml: not valid YAML" in rows["bad"]["error"] and not (out / "bad").exists()
    for name in ("c0", "c1", "c2"):
        row = rows[name]
        assert row["status"] == "done" and row["model"] == "fmbrdf" and row["materials"] == "1"
        assert 1.0 < float(row["ior"]) < 3.0 and 0.0 < float(row["alpha"]) < 1.0
        assert 0.0 < float(row["normal_mean_deg"]) < 10.0  # the capture has ground truth
        assert row["heldout_s0_rel_rmse"] == "" and float(row["time_s"]) > 0  # validation: none
        assert is_result_folder(out / name)
        params = json.loads((out / name / "params.json").read_text())
        assert int(row["warnings"]) >= len(params["warnings"])
        assert all(text in row["warning_list"] for text in params["warnings"])
        log = (out / name / LOG_FILE).read_text()  # the per-capture log, inside the atomic result
        assert "stage recovery" in log and "stage report" in log
        assert params["capture"]["source"] == str(caps / name)
    failed = json.loads((out / "failed.json").read_text())
    assert failed["format"] == FAILED_FORMAT and [f["capture"] for f in failed["failed"]] == ["bad"]
    assert failed["failed"][0]["type"] == "CaptureError" and failed["failed"][0]["exit_status"] == 2
    assert json.loads((out / "batch.json").read_text())["format"] == BATCH_FORMAT
    index = (out / "index.html").read_text()
    assert index.count('<a href="c') == 3 and "CaptureError" in index
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # nothing half-written

    # resume: the complete results are skipped (untouched), the failed one is run again
    mtimes = {name: (out / name / "params.json").stat().st_mtime_ns for name in ("c0", "c1", "c2")}
    shutil.rmtree(caps / "bad")
    shutil.copytree(capture, caps / "bad")
    assert main(["batch", str(config), str(caps / "*"), "--out", str(out), "-q"]) == 0
    rows = _rows(out)
    assert rows["bad"]["status"] == "done" and all(rows[n]["status"] == "complete" for n in mtimes)
    assert {n: (out / n / "params.json").stat().st_mtime_ns for n in mtimes} == mtimes
    assert read_failed(out) == {}


def test_out_must_be_a_batch_folder_and_the_config_has_no_input(tmp_path: Path, capture: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    caps, config = make_batch(tmp_path, capture, good=1)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    assert main(["batch", str(config), str(caps / "c0"), "--out", str(mine), "-q"]) == 1
    assert "is not a polarshape batch folder" in capsys.readouterr().err
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    assert main(["batch", str(config), str(caps / "c0"), "--out", str(caps), "-q"]) == 1  # it holds the input
    with_input = tmp_path / "with_input.yaml"
    with_input.write_text(yaml.safe_dump({**BATCH_CONFIG, "input": {"type": "capture", "path": "caps/c0"}}))
    assert main(["batch", str(with_input), str(caps / "c0"), "--out", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "- input: a batch configuration has no input" in err and not (tmp_path / "o").exists()


def test_batch_config_is_validated_like_a_run_config(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"recovery\.modl: unknown key \(did you mean 'model'\?\)"):
        parse_batch_config({"recovery": {"modl": "fmbrdf"}}, "b.yaml")
    path = tmp_path / "b.yaml"
    path.write_text(yaml.safe_dump(BATCH_CONFIG))
    batch = load_batch_config(path)
    assert batch.input is None
    (tmp_path / "cap").mkdir()
    (tmp_path / "cap" / "capture.yaml").write_text("format: polarshape-capture/1\n")
    run = batch.for_capture(tmp_path / "cap")
    assert run.input.type == "capture" and run.input.path == str(tmp_path / "cap")
    assert run.model_dump(exclude={"input"}) == batch.model_dump(exclude={"input"})
    with pytest.raises(ConfigError, match="is not a capture folder"):
        batch.for_capture(tmp_path / "missing")


def test_find_captures(tmp_path: Path) -> None:
    for name in ("a/x", "a/y", "b/x", "a/z.txt"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).mkdir() if not name.endswith(".txt") else (tmp_path / name).write_text("")
    found = find_captures([str(tmp_path / "a" / "*"), str(tmp_path / "a" / "x")])
    assert found == {"x": tmp_path / "a" / "x", "y": tmp_path / "a" / "y"}  # files ignored, each folder once
    with pytest.raises(CaptureError, match="two captures are named 'x'"):
        find_captures([str(tmp_path / "a" / "x"), str(tmp_path / "b" / "x")])
    with pytest.raises(CaptureError, match="matches no folder"):
        find_captures([str(tmp_path / "nothing*")])
    with pytest.raises(CaptureError, match="is not a folder"):
        find_captures([str(tmp_path / "a" / "z.txt")])


def test_plan_local_never_oversubscribes() -> None:
    assert plan_local(16, cores=8) == (8, 1)
    assert plan_local(3, cores=8) == (3, 1)  # never more workers than captures
    assert plan_local(16, workers=2, cores=8) == (2, 4)
    assert plan_local(16, threads=2, cores=8) == (4, 2)
    with pytest.raises(ConfigError, match="--workers 4 x --threads-per-worker 4 = 16 threads on 8 cores"):
        plan_local(16, workers=4, threads=4, cores=8)
    with pytest.raises(ConfigError, match="--workers must be at least 1"):
        plan_local(16, workers=0, cores=8)


def test_ray_gpus_and_install_hint(monkeypatch: pytest.MonkeyPatch) -> None:
    assert ray_uses_gpus("auto", 2) and ray_uses_gpus("cuda", 1)
    assert not ray_uses_gpus("auto", 0) and not ray_uses_gpus("cpu", 4)
    with pytest.raises(DeviceError, match="the Ray cluster has no GPU"):
        ray_uses_gpus("cuda", 0)
    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    with pytest.raises(PipelineError, match=r"pip install 'polarshape\[cluster\]'"):
        import_ray()


def test_summary_row_reads_optional_sections() -> None:
    params = {
        "model": "fmbrdf", "params": {"ior": 1.5, "alpha": 0.3}, "metrics": {}, "timings_s": {"total": 2.0},
        "warnings": ["FitResidualWarning: fit residual 36x the noise"], "report": ["report.html", "report"],
        "validation": {"models": {"fmbrdf": {"s0_rel_rmse": 0.021}, "lambertian": {"s0_rel_rmse": 0.09}}},
        "checks": {"warnings": [{"name": "FitResidualWarning", "message": "fit residual 36x the noise"},
                                {"name": "ParameterBoundWarning", "message": "beta at its bound"}]},
    }
    row = summary_row("cup", "/data/cup", "done", params)
    assert row["heldout_s0_rel_rmse"] == 0.021 and row["normal_mean_deg"] is None
    assert row["warnings"] == 2 and "ParameterBoundWarning: beta at its bound" in row["warning_list"]
    assert row["report"] == "cup/report.html" and row["time_s"] == 2.0
    bare = summary_row("cup", "/data/cup", "done", {"model": "lambertian", "params": {}})
    assert bare["heldout_s0_rel_rmse"] is None and bare["ior"] is None and bare["warnings"] == 0
    with pytest.raises(ValueError, match="status must be one of"):
        summary_row("cup", "/data/cup", "finished")


@pytest.mark.slow
def test_a_killed_batch_resumes_with_only_what_was_missing(tmp_path: Path, capture: Path) -> None:
    """SIGKILL of the batch process after its first result: its worker stops and removes its
    half-written folder; the same command then runs only the captures without a result."""
    caps, config = make_batch(tmp_path, capture, good=3)
    shutil.rmtree(caps / "bad")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "polarshape.cli", "batch", str(config), str(caps / "*"), "--out", str(out),
           "--workers", "1", "-q"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    # kill once the first result is in the folders *and* the tables (between the two the tables lag by
    # one capture until the next write: the batch writes them after each outcome reaches it)
    while proc.poll() is None and time.monotonic() < deadline and not _recorded_done(out):
        time.sleep(0.02)
    assert proc.poll() is None, "the batch ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(30)
    first = {p.parent.name: p.stat().st_mtime_ns for p in out.glob("c*/params.json")}
    assert 1 <= len(first) < 3
    deadline = time.monotonic() + 20  # the orphaned worker notices within a second and cleans up
    while list(out.glob(".*partial*")) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not list(out.glob(".*partial*"))
    rows = _rows(out)  # consistent with the folders as of the kill
    assert {n for n, r in rows.items() if r["status"] == "done"} == set(first)

    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    assert f"{3 - len(first)} done; {len(first)} complete from an earlier run (skipped)" in done.stdout
    assert {n: (out / n / "params.json").stat().st_mtime_ns for n in first} == first
    rows = _rows(out)
    assert all(rows[n]["status"] == ("complete" if n in first else "done") for n in rows) and len(rows) == 3
