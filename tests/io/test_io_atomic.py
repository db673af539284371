"""Tests of polarshape.io.atomic: atomic files and folders, no silent overwrite."""

from __future__ import annotations

from pathlib import Path

import pytest

from polarshape.io.atomic import (
    OutputExistsError,
    atomic_directory,
    atomic_path,
    atomic_write_bytes,
    atomic_write_text,
)


def test_write_bytes_and_text(tmp_path: Path) -> None:
    assert atomic_write_bytes(tmp_path / "sub" / "a.bin", b"\x00\x01") == tmp_path / "sub" / "a.bin"
    assert (tmp_path / "sub" / "a.bin").read_bytes() == b"\x00\x01"
    atomic_write_text(tmp_path / "b.txt", "é")
    assert (tmp_path / "b.txt").read_text("utf-8") == "é"


def test_refuses_to_overwrite_a_file(tmp_path: Path) -> None:
    path = tmp_path / "a.txt"
    atomic_write_text(path, "old")
    with pytest.raises(OutputExistsError, match="overwrite=True"):
        atomic_write_text(path, "new")
    assert path.read_text() == "old"
    atomic_write_text(path, "new", overwrite=True)
    assert path.read_text() == "new"


def test_failed_write_leaves_nothing(tmp_path: Path) -> None:
    path = tmp_path / "a.npy"
    with pytest.raises(RuntimeError), atomic_path(path) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("writer crashed")
    assert list(tmp_path.iterdir()) == []


def test_failed_overwrite_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "a.txt"
    atomic_write_text(path, "old")
    with pytest.raises(RuntimeError), atomic_path(path, overwrite=True) as tmp:
        tmp.write_text("partial")
        raise RuntimeError("crash")
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_writer_that_removes_its_temporary_file(tmp_path: Path) -> None:
    with pytest.raises(OSError, match="removed its temporary file"), atomic_path(tmp_path / "a.txt") as tmp:
        tmp.unlink()
    assert not (tmp_path / "a.txt").exists()


def test_temporary_name_keeps_the_suffix(tmp_path: Path) -> None:
    with atomic_path(tmp_path / "image.png") as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path and tmp.name != "image.png"
        tmp.write_bytes(b"x")


def test_directory_appears_only_when_complete(tmp_path: Path) -> None:
    out = tmp_path / "result"
    with atomic_directory(out) as tmp:
        (tmp / "a.txt").write_text("a")
        assert not out.exists()
    assert (out / "a.txt").read_text() == "a"
    assert [p.name for p in tmp_path.iterdir()] == ["result"]


def test_directory_failure_keeps_old_folder(tmp_path: Path) -> None:
    out = tmp_path / "result"
    with atomic_directory(out) as tmp:
        (tmp / "old.txt").write_text("old")
    with pytest.raises(OutputExistsError), atomic_directory(out):
        pass
    with pytest.raises(RuntimeError), atomic_directory(out, overwrite=True) as tmp:
        (tmp / "new.txt").write_text("new")
        raise RuntimeError("crash")
    assert sorted(p.name for p in out.iterdir()) == ["old.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["result"]
    with atomic_directory(out, overwrite=True) as tmp:
        (tmp / "new.txt").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["new.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["result"]


def test_protected_folder_is_never_replaced(tmp_path: Path) -> None:
    inputs = tmp_path / "capture"
    inputs.mkdir()
    (inputs / "capture.yaml").write_text("x")

    def is_capture(p: Path) -> str | None:
        return "it holds input data" if (p / "capture.yaml").exists() else None

    with (
        pytest.raises(OutputExistsError, match="holds input data"),
        atomic_directory(inputs, overwrite=True, protect=is_capture),
    ):
        pass
    assert (inputs / "capture.yaml").read_text() == "x"


def test_stale_partials_of_dead_processes_are_removed(tmp_path: Path) -> None:
    """A run killed outright (SIGKILL) leaves .NAME.partial-PID-*; the next write to the same
    destination removes it once PID is gone, and keeps a live process's and other names'."""
    import os
    import subprocess

    dead = subprocess.Popen(["true"])
    dead.wait()
    stale = tmp_path / f".result.partial-{dead.pid}-abc"
    live = tmp_path / f".result.partial-{os.getpid()}-def"
    other = tmp_path / f".other.partial-{dead.pid}-ghi"
    for folder in (stale, live, other):
        folder.mkdir()
        (folder / "normals.npy").write_text("half")
    with atomic_directory(tmp_path / "result") as tmp:
        (tmp / "a.txt").write_text("a")
    assert not stale.exists() and live.exists() and other.exists()
    assert (tmp_path / "result" / "a.txt").read_text() == "a"
