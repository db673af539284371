"""Tests of polarshape.io.atomic: atomic files and folders, no silent overwrite, errors that name the
folder and the cause (a file in the way, no permission, a full disk), permissions from the umask."""

from __future__ import annotations

import errno
import os
import re
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from polarshape.cli.errors import exit_status
from polarshape.errors import OutputPathError, OutputWriteError
from polarshape.io.atomic import (
    OutputExistsError,
    atomic_directory,
    atomic_path,
    atomic_write_bytes,
    atomic_write_text,
    remove_stale_temporaries,
)
from polarshape.io.capture import Capture, parse_capture_spec, write_capture


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


# --- a file in the way, no permission, a full disk -----------------------------------------------


def _enospc(*args: object, **kwargs: object) -> None:
    raise OSError(errno.ENOSPC, "No space left on device")


def test_a_file_where_a_folder_must_be_is_named(tmp_path: Path) -> None:
    (tmp_path / "afile").write_text("")
    for write in (lambda p: atomic_write_text(p / "x.txt", "x"), lambda p: atomic_directory(p).__enter__()):
        with pytest.raises(OutputPathError, match=re.escape(f"{tmp_path / 'afile'} is a file, not a folder")) as info:
            write(tmp_path / "afile" / "sub")
        assert isinstance(info.value, NotADirectoryError) and exit_status(info.value) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_no_permission_to_create_the_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise PermissionError(errno.EACCES, "Permission denied", str(args[0]) if args else None)

    monkeypatch.setattr(os, "mkdir", refuse)
    with pytest.raises(OutputWriteError, match=re.escape(f"cannot create {tmp_path / 'ro'}: permission denied")) as info:
        atomic_write_text(tmp_path / "ro" / "x.txt", "x")
    assert exit_status(info.value) == 3
    monkeypatch.undo()
    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    with pytest.raises(OutputWriteError, match=re.escape(f"cannot create {tmp_path / 'res'}: permission denied")):
        with atomic_directory(tmp_path / "res"):
            pass
    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(OutputWriteError, match=re.escape(f"cannot create {tmp_path / 'x.txt'}: permission denied")):
        atomic_write_text(tmp_path / "x.txt", "x")
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_names_the_folder_and_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(Path, "write_bytes", _enospc)
    with pytest.raises(OutputWriteError, match=re.escape(
            f"no space left on device while writing {tmp_path / 'a.txt'}: free space or choose another --out")) as info:
        atomic_write_text(tmp_path / "a.txt", "x")
    assert exit_status(info.value) == 3 and info.value.errno == errno.ENOSPC
    with pytest.raises(OutputWriteError, match=re.escape(
            f"no space left on device while writing {tmp_path / 'res'} (params.json): free space or choose another --out")):
        with atomic_directory(tmp_path / "res") as work:
            atomic_write_text(work / "params.json", "{}")
    assert list(tmp_path.iterdir()) == []  # no .res.partial-*, no temporary file


def test_an_error_reading_an_input_is_left_as_it_is(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError), atomic_directory(tmp_path / "res"):
        (tmp_path / "missing.txt").read_text()
    assert list(tmp_path.iterdir()) == []


# --- permissions follow the umask ----------------------------------------------------------------


@pytest.fixture
def umask_022() -> Iterator[None]:
    old = os.umask(0o022)
    try:
        yield
    finally:
        os.umask(old)


@pytest.mark.usefixtures("umask_022")
def test_written_files_and_folders_follow_the_umask(tmp_path: Path) -> None:
    path = atomic_write_text(tmp_path / "a.txt", "x")
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    with atomic_directory(tmp_path / "res") as work:
        atomic_write_text(work / "params.json", "{}")
        with atomic_path(work / "b.npy") as tmp:
            tmp.write_bytes(b"x")
    assert stat.S_IMODE((tmp_path / "res").stat().st_mode) == 0o755
    assert {p.name: stat.S_IMODE(p.stat().st_mode) for p in (tmp_path / "res").iterdir()} == {
        "params.json": 0o644, "b.npy": 0o644}
    os.umask(0o077)
    assert stat.S_IMODE(atomic_write_text(tmp_path / "private.txt", "x").stat().st_mode) == 0o600


@pytest.mark.usefixtures("umask_022")
def test_a_written_capture_follows_the_umask(tmp_path: Path) -> None:
    frames = np.full((2, 8, 8), 100, dtype=np.uint16)
    spec = parse_capture_spec({"format": "polarshape-capture/1", "camera": {"projection": "orthographic", "bit_depth": 12},
                               "lights": [{"direction": [0.0, 0.0, -1.0], "frame": "frames/000.png"},
                                          {"direction": [0.6, 0.0, -0.8], "frame": "frames/001.png"}]})
    write_capture(tmp_path / "cap", Capture(spec=spec, frames=frames))
    modes = {str(p.relative_to(tmp_path)): stat.S_IMODE(p.stat().st_mode) for p in [tmp_path / "cap", *(tmp_path / "cap").rglob("*")]}
    assert modes == {name: 0o755 if (tmp_path / name).is_dir() else 0o644 for name in modes}
    assert "cap/capture.yaml" in modes and "cap/frames/000.png" in modes


def test_stale_temporaries_of_a_killed_writer_are_removed_and_live_ones_kept(tmp_path: Path) -> None:
    """A temporary that atomic_path made for a file and a killed process left is removed once old;
    a young one (a live writer's), other files' temporaries and the file itself are kept."""
    target = atomic_write_text(tmp_path / "summary.csv", "a,b\n")
    with atomic_path(target, overwrite=True) as live:  # the real naming of a temporary of summary.csv
        live.write_text("x")
        stale = live.with_name(live.name.replace(live.name.split(".")[2], "dead"))
        stale.write_text("old")
        os.utime(stale, (1.0, 1.0))
        other = tmp_path / ".failed.dead.tmp.json"
        other.write_text("old")
        os.utime(other, (1.0, 1.0))
        remove_stale_temporaries(target)
        assert live.exists() and not stale.exists() and other.exists()
    assert target.read_text() == "x"
