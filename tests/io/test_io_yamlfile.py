"""polarshape.io.yamlfile: the one YAML reader; a key given twice is an error naming the file, the
key path and both lines, in every file polarshape reads (it used to keep the last value silently)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest
import yaml

from polarshape.acquisition.calibrate import update_capture_yaml
from polarshape.acquisition.session import load_session_config
from polarshape.cli import main
from polarshape.config import load_run_config
from polarshape.errors import CaptureError, ConfigError
from polarshape.io.capture import load_capture
from polarshape.io.yamlfile import load_yaml
from polarshape.scene.config import load_scene_config

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("a: 1\nb: 2\na: 3\n", "f.yaml: line 3: key 'a' appears twice (first on line 1)"),
        ("s:\n  x: 1\n  y: 2\n  x: 3\n", "f.yaml: line 4: key 's.x' appears twice (first on line 2)"),
        ("lights:\n  - {d: 1}\n  - {d: 1, i: 2, d: 3}\n", "f.yaml: line 3: key 'lights[1].d' appears twice (first on line 3)"),
        ("1: a\n0x1: b\n", "key '0x1' appears twice (first on line 1)"),  # the same key as YAML reads it
    ],
)
def test_a_duplicate_key_is_named_with_its_lines(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(message) + r"; YAML would keep only the last value: remove one$"):
        load_yaml("f.yaml", text=text)


def test_everything_else_reads_as_safe_load() -> None:
    for text in ("a: 1\nb: [1, 2]\nc: {d: .inf}\n", "base: &b {k: 1, m: 2}\nd:\n  <<: *b\n  k: 3\n", "r: &r [1]\ns: *r\n",
                 "- a\n- a\n", ""):
        assert load_yaml("f.yaml", text=text) == yaml.safe_load(text)


def test_other_problems_are_one_line_errors_of_the_callers_kind(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match=r"^f.yaml: not valid YAML: line 2, column 1: expected ',' or ']'[^\n]*$"):
        load_yaml("f.yaml", text="a: [1\n", error=CaptureError)
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(b"a: \xff\n")
    with pytest.raises(ConfigError, match="bad.yaml: not UTF-8 text"):
        load_yaml(bad)
    with pytest.raises(ConfigError, match="nope.yaml: cannot read it"):
        load_yaml(tmp_path / "nope.yaml")


# --- every reader uses it ----------------------------------------------------------------------


def test_run_config_with_a_duplicate_section(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "cap").mkdir()
    config = tmp_path / "run.yaml"
    config.write_text("input: {type: capture, path: cap}\nrecovery: {model: fmbrdf}\nmesh: {obj: false}\n"
                      "recovery: {max_outer_iterations: 3}\n")
    with pytest.raises(ConfigError, match=r"run.yaml: line 4: key 'recovery' appears twice \(first on line 2\)"):
        load_run_config(config)
    assert main(["run", str(config), "--out", str(tmp_path / "res")]) == 2
    err = capsys.readouterr().err
    assert "key 'recovery' appears twice" in err and err.count("\n") == 1


def test_scene_with_a_duplicate_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = tmp_path / "scene.yaml"
    scene.write_text((REPO / "configs" / "scenes" / "sphere.yaml").read_text().replace(
        "  exposure_us: 10000", "  exposure_us: 10000\n  exposure_us: 20000", 1))
    with pytest.raises(ConfigError, match=r"scene.yaml: line \d+: key 'camera.exposure_us' appears twice"):
        load_scene_config(scene)
    assert main(["simulate", str(scene), "--out", str(tmp_path / "cap")]) == 2
    assert "camera.exposure_us" in capsys.readouterr().err and not (tmp_path / "cap").exists()


def test_capture_yaml_with_a_duplicate_key(tmp_path: Path) -> None:
    (tmp_path / "capture.yaml").write_text("format: polarshape-capture/1\ncamera: {bit_depth: 12}\n"
                                           "camera: {bit_depth: 8}\nlights: []\n")
    with pytest.raises(CaptureError, match=r"capture.yaml: line 3: key 'camera' appears twice"):
        load_capture(tmp_path)
    with pytest.raises(CaptureError, match=r"capture.yaml: line 3: key 'camera' appears twice"):
        update_capture_yaml(tmp_path, lights=[[0.0, 0.0, -1.0]])


def test_session_file_with_a_duplicate_key(tmp_path: Path) -> None:
    session = tmp_path / "session.yaml"
    shutil.copy(REPO / "configs" / "sessions" / "fake_camera.yaml", session)
    session.write_text(session.read_text() + "\ncamera: {backend: simulated}\n")
    with pytest.raises(ConfigError, match=r"session.yaml: line \d+: key 'camera' appears twice"):
        load_session_config(session)
