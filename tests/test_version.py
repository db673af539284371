"""Tests of polarshape.__version__, ``polarshape --version`` and the lazy public face."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import polarshape

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


def _pyproject_version() -> str:
    # [project] holds the only top-level ``version =`` line (no tomllib: Python 3.10 has none).
    found = re.search(r'^version = "([^"]+)"$', PYPROJECT.read_text(), re.MULTILINE)
    assert found, "no version in pyproject.toml"
    return found.group(1)


def test_version_matches_pyproject() -> None:
    assert polarshape.__version__ == _pyproject_version()


def test_uninstalled_source_tree_falls_back_to_the_pyproject_version() -> None:
    code = (
        "import importlib.metadata as m\n"
        "def not_installed(name):\n"
        "    raise m.PackageNotFoundError(name)\n"
        "m.version = not_installed\n"
        "import polarshape\n"
        "print(polarshape.__version__)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == _pyproject_version()


def test_cli_prints_the_version() -> None:
    cmd = [sys.executable, "-m", "polarshape.cli", "--version"]
    result = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == f"polarshape {_pyproject_version()}"


def test_public_names_are_imported_on_first_use() -> None:
    code = (
        "import sys, polarshape; assert 'torch' not in sys.modules; "
        "from polarshape import fmbrdf_stokes, stokes_from_mosaic, run_pipeline; "
        "from polarshape.brdf import fmbrdf_stokes as f; from polarshape.imaging.demosaic import stokes_from_mosaic as s; "
        "from polarshape.pipeline import run_pipeline as r; "
        "assert (fmbrdf_stokes, stokes_from_mosaic, run_pipeline) == (f, s, r); "
        "assert {'run_pipeline', 'recover_normals', 'fmbrdf_stokes', 'stokes_from_mosaic'} <= set(dir(polarshape))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False, timeout=120)
    assert result.returncode == 0, result.stderr
