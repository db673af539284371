"""Atomic file and folder writes: a reader never sees a half-written output, and nothing is
written over a user's file unless asked.

Files are written to a temporary name in the destination folder and renamed into place
(``os.replace`` is atomic on POSIX within one file system). Folders are assembled under a hidden
temporary name beside the destination, ``.NAME.partial-PID-XXXX``, and renamed once complete; an
interrupted process removes it on the way out (Ctrl-C, and SIGTERM through the command line's
handler), and a process killed outright (SIGKILL) leaves one that the next write to the same
destination removes, once its process ``PID`` is gone.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from polarshape.errors import OutputExistsError

logger = logging.getLogger(__name__)


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


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def remove_stale_partials(path: Path) -> list[Path]:
    """Remove the ``.NAME.partial-PID-*`` folders beside ``path`` whose process is gone (a run
    killed before it could clean up); live processes' folders are kept. Returns what was removed."""
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.partial-(\d+)-")
    removed = []
    if not path.parent.is_dir():
        return removed
    for entry in path.parent.iterdir():
        match = pattern.match(entry.name)
        if match and entry.is_dir() and not _process_alive(int(match.group(1))):
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
            logger.info("removed %s, left by an interrupted run", entry)
    return removed


@contextlib.contextmanager
def atomic_directory(
    path: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    protect: Callable[[Path], str | None] | None = None,
) -> Iterator[Path]:
    """Build a folder under a temporary name and move it to ``path`` only when complete.

    Args:
        path: the final folder.
        overwrite: replace an existing folder at ``path`` (it is removed only after the new one is
            complete, so an interrupted run leaves the old one intact).
        protect: optional check of ``path``, called whether it exists or not: a reason (text) why
            nothing may be written there (e.g. it is, holds or lies inside the run's input), or None.
            A reason refuses the folder whatever ``overwrite`` says.

    Yields:
        The temporary folder to write into.
    """
    path = Path(path).absolute()
    reason = protect(path) if protect is not None else None
    if reason:
        raise OutputExistsError(f"{path}: {reason}; refusing to write a result there")
    _check_destination(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_partials(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.partial-{os.getpid()}-", dir=path.parent))
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
