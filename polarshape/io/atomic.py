"""Atomic file and folder writes: a reader never sees a half-written output, and nothing is
written over a user's file unless asked.

Files are written to a temporary name in the destination folder and renamed into place
(``os.replace`` is atomic on POSIX within one file system). Folders are assembled under a hidden
temporary name beside the destination and renamed once complete.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from polarshape.errors import OutputExistsError


def _check_destination(path: Path, overwrite: bool) -> None:
    if path.exists() and not overwrite:
        raise OutputExistsError(
            f"{path} already exists; refusing to overwrite it (pass overwrite=True / --overwrite, "
            "or choose another output path)"
        )


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary file path beside ``path``; on success rename it to ``path``.

    The writer writes to the yielded path (any library that takes a file name works). On an
    exception the temporary file is removed and ``path`` is left untouched.

    Example:
        >>> with atomic_path("out/normals.npy", overwrite=True) as tmp:  # doctest: +SKIP
        ...     np.save(tmp, normals)
    """
    path = Path(path)
    _check_destination(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if not tmp.exists():
            raise OSError(f"the writer removed its temporary file; nothing was written to {path}")
        _check_destination(path, overwrite)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, *, overwrite: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically. Returns the final path."""
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike[str], text: str, *, overwrite: bool = False) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically. Returns the final path."""
    return atomic_write_bytes(path, text.encode("utf-8"), overwrite=overwrite)


@contextlib.contextmanager
def atomic_directory(
    path: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    protect: Callable[[Path], bool] | None = None,
) -> Iterator[Path]:
    """Build a folder under a temporary name and move it to ``path`` only when complete.

    Args:
        path: the final folder.
        overwrite: replace an existing folder at ``path`` (it is removed only after the new one is
            complete, so an interrupted run leaves the old one intact).
        protect: optional predicate; if it returns True for ``path`` the folder is never replaced
            (e.g. it is the input capture of the run), whatever ``overwrite`` says.

    Yields:
        The temporary folder to write into.
    """
    path = Path(path).absolute()
    if protect is not None and path.exists() and protect(path):
        raise OutputExistsError(f"{path} holds input data; refusing to write a result over it")
    _check_destination(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.partial-", dir=path.parent))
    try:
        yield tmp
        _check_destination(path, overwrite)
        if path.exists():
            old = path.with_name(f".{path.name}.old-{os.getpid()}")
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
