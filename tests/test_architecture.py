"""The layout of ARCHITECTURE.md holds: no module imports a stage after it in the data flow, and
tests use public names only."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Stages in data-flow order (ARCHITECTURE.md); a module may import only from its stage or earlier ones.
STAGES: tuple[tuple[str, ...], ...] = (
    ("errors", "checks", "metrics"),
    ("cameras", "lights"),
    ("imaging",),
    ("brdf",),
    ("io", "demo", "inspect_frame"),
    ("scene",),
    ("acquisition",),
    ("recover",),
    ("normals",),
    ("surface",),
    ("nearfield",),
    ("report",),
    ("config", "pipeline", "measure"),
    ("cli", "batch"),
)


def stage_of(module: str) -> int | None:
    """The stage of ``polarshape.<part>...`` (None for the package itself and its ``__version__``)."""
    parts = module.split(".")
    if parts[0] != "polarshape" or len(parts) < 2 or parts[1].startswith("__"):
        return None
    for rank, names in enumerate(STAGES):
        if parts[1] in names:
            return rank
    raise AssertionError(f"{module} is in no stage of ARCHITECTURE.md: add it there and to STAGES")


def imported_modules(path: Path) -> list[tuple[str, int]]:
    """(module, line) of every absolute polarshape import in a file (``from a import b`` gives a.b too)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out += [(node.module, node.lineno)] + [(f"{node.module}.{a.name}", node.lineno) for a in node.names]
        elif isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
    return [(m, line) for m, line in out if m.startswith("polarshape.")]


def test_no_module_imports_a_later_stage() -> None:
    problems = []
    for path in sorted((ROOT / "polarshape").rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        own = stage_of(module)
        if own is None:
            continue
        for name, line in imported_modules(path):
            other = stage_of(name)
            if other is not None and other > own:
                problems.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    assert not problems, "imports against the data flow:\n" + "\n".join(problems)


def test_tests_import_public_names_only() -> None:
    problems = []
    for path in sorted((ROOT / "tests").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("polarshape"):
                private = [a.name for a in node.names if a.name.startswith("_")]
                if private or any(p.startswith("_") for p in (node.module or "").split(".")):
                    problems.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.module} {private}")
    assert not problems, "tests importing private names:\n" + "\n".join(problems)


def test_the_stage_check_fails_on_a_backward_import(tmp_path: Path) -> None:
    """The check itself: an imaging module importing the pipeline is caught."""
    bad = tmp_path / "bad.py"
    bad.write_text("from polarshape.pipeline import run_pipeline\n")
    (name, _), *_ = imported_modules(bad)
    assert stage_of(name) > stage_of("polarshape.imaging.stokes")
    with pytest.raises(AssertionError, match="no stage"):
        stage_of("polarshape.unknown_module")


#: Import name of each distribution whose name differs from it.
_IMPORT_NAMES = {"opencv-contrib-python-headless": "cv2", "pyyaml": "yaml", "pyserial": "serial"}


def test_every_dependency_is_used() -> None:
    """No unused dependency: each [project] dependency of pyproject.toml is imported by the package."""
    text = (ROOT / "pyproject.toml").read_text()
    block = text.split("dependencies = [", 1)[1].split("]", 1)[0]
    names = [line.strip().strip('",').split(">")[0].split("<")[0].split("=")[0].strip()
             for line in block.splitlines() if line.strip().startswith('"')]
    imported = set()
    for path in (ROOT / "polarshape").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                imported.add(node.module.split(".")[0])
    assert len(names) > 5, names
    unused = [n for n in names if _IMPORT_NAMES.get(n.lower(), n) not in imported]
    assert not unused, f"declared but imported nowhere in polarshape/: {unused}"
