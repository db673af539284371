"""Atomic file and folder writes: a reader never sees a half-written output, and nothing is
written over a user's file unless asked.

Files are written to a temporary name in the destination folder and renamed into place
(``os.replace`` is atomic on POSIX within one file system). Folders are assembled under a hidden
temporary name beside the destination, ``.NAME.partial-PID-XXXX``, and renamed once complete; an
interrupted process removes it on the way out (Ctrl-C, and SIGTERM through the command line's
handler), and a process killed outright (SIGKILL) leaves one that the next write to the same
destination removes, once its process ``PID`` is gone.

Errors name the path and the cause, and nothing half-written is kept: a file where a folder must
be is :class:`~polarshape.errors.OutputPathError` (exit status 2); no permission, a read-only file
system or a full disk while writing is :class:`~polarshape.errors.OutputWriteError` (exit status 3).

Permissions follow the umask, as for any file a program creates (``tempfile`` would make the
temporary names 0600 and 0700, private to their owner): a file is ``0o666 & ~umask``, a folder
``0o777 & ~umask`` (0644 and 0755 with the usual umask 022).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from polarshape.errors import OutputExistsError, OutputPathError, OutputWriteError

logger = logging.getLogger(__name__)


def current_umask() -> int:
    """The process umask (e.g. ``0o022``).

    Read from ``/proc/self/status`` where Linux shows it, which changes nothing; elsewhere POSIX can
    only read it by setting it, so it is set to a private ``0o077`` and restored at once (a file
    another thread creates in between is then private rather than too open).
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    old = os.umask(0o077)
    os.umask(old)
    return old


def _write_error(exc: OSError, path: Path, detail: str = "") -> OutputWriteError | None:
    """The :class:`OutputWriteError` for ``exc`` raised while creating or writing ``path`` (``detail``:
    the file inside a folder being written), or None if ``exc`` is not about where we write."""
    if exc.errno == errno.ENOSPC:
        message = f"no space left on device while writing {path}{detail}: free space or choose another --out"
    elif exc.errno == errno.EDQUOT:
        message = f"disk quota exceeded while writing {path}{detail}: free space or choose another --out"
    elif exc.errno in (errno.EACCES, errno.EPERM):
        message = f"cannot create {path}{detail}: permission denied; choose another --out (a folder you may write in)"
    elif exc.errno == errno.EROFS:
        message = f"cannot create {path}{detail}: read-only file system; choose another --out"
    else:
        return None
    return OutputWriteError(message, errno=exc.errno, path=str(path))


@contextlib.contextmanager
def _named_write_errors(path: Path) -> Iterator[None]:
    """Inside, an ``OSError`` about where we write (:func:`_write_error`) becomes an
    :class:`OutputWriteError` naming ``path``; any other error passes unchanged."""
    try:
        yield
    except OSError as exc:
        error = _write_error(exc, path)
        if error is None:
            raise
        raise error from exc


def _inside(exc: OSError, folder: Path) -> str | None:
    """The file of ``exc`` relative to ``folder`` if it lies there (written by us), else None."""
    name = getattr(exc, "path", None) or exc.filename
    if name is None:
        return None
    try:
        return str(Path(os.fsdecode(name)).absolute().relative_to(folder.absolute()))
    except ValueError:
        return None


def _make_folder(folder: Path, target: Path) -> None:
    """``mkdir -p folder`` (to write ``target`` in), failing with a message that names the file in
    the way or the cause."""
    for above in (folder, *folder.parents):
        if above.is_dir():
            break
        if above.is_symlink() and not above.exists():
            raise OutputPathError(f"{above} is a broken symbolic link, not a folder, so {target} cannot be created "
                                  "there; remove the link or choose another output path")
        if above.exists():
            raise OutputPathError(f"{above} is a file, not a folder, so {target} cannot be created there; "
                                  "choose another output path")
    with _named_write_errors(folder):
        folder.mkdir(parents=True, exist_ok=True)


def check_destination(path: Path, overwrite: bool) -> None:
    """Refuse an existing ``path`` unless ``overwrite`` (:class:`OutputExistsError`, exit status 1)."""
    if path.exists() and not overwrite:
        raise OutputExistsError(
            f"{path} already exists; refusing to overwrite it (pass overwrite=True / --overwrite, "
            "or choose another output path)"
        )


#: How :func:`atomic_path` names its temporary file beside ``path``: ``.<stem>.XXXX.tmp<suffix>``.
_TMP_PREFIX, _TMP_SUFFIX = ".{stem}.", ".tmp{suffix}"


def remove_stale_temporaries(path: str | os.PathLike[str], min_age_s: float = 60.0) -> None:
    """Remove the temporary files :func:`atomic_path` made for ``path`` and a process killed outright
    (SIGKILL) left behind, once older than ``min_age_s`` (a live writer's file is younger)."""
    path = Path(path)
    now = time.time()
    pattern = _TMP_PREFIX.format(stem=path.stem) + "*" + _TMP_SUFFIX.format(suffix=path.suffix)
    for tmp in path.parent.glob(pattern):
        with contextlib.suppress(OSError):
            if now - tmp.stat().st_mtime > min_age_s:
                tmp.unlink()


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
    check_destination(path, overwrite)
    _make_folder(path.parent, path)
    with _named_write_errors(path):
        fd, tmp_name = tempfile.mkstemp(prefix=_TMP_PREFIX.format(stem=path.stem),
                                        suffix=_TMP_SUFFIX.format(suffix=path.suffix), dir=path.parent)
    tmp = Path(tmp_name)
    try:
        os.fchmod(fd, 0o666 & ~current_umask())  # mkstemp makes it 0600
        os.close(fd)
        try:
            yield tmp
        except OSError as exc:
            # a full disk whoever reports it; a refusal only when it is about the file we write
            ours = exc.errno in (errno.ENOSPC, errno.EDQUOT) or _inside(exc, tmp.parent) is not None
            error = _write_error(exc, path) if ours and not isinstance(exc, OutputWriteError) else None
            if error is None:
                raise
            raise error from exc
        if not tmp.exists():
            raise OSError(f"the writer removed its temporary file; nothing was written to {path}")
        check_destination(path, overwrite)
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
        raise OutputExistsError(f"{path}: {reason}; refusing to write there")
    check_destination(path, overwrite)
    _make_folder(path.parent, path)
    remove_stale_partials(path)
    with _named_write_errors(path):
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.partial-{os.getpid()}-", dir=path.parent))
    try:
        os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp makes it 0700
        try:
            yield tmp
        except OSError as exc:
            # named after the folder the user asked for, not the hidden one being assembled
            inside = _inside(exc, tmp)
            if inside is None and isinstance(exc, OutputWriteError) and exc.path is not None:
                inside = _inside(OSError(None, None, exc.path), tmp)
            ours = exc.errno in (errno.ENOSPC, errno.EDQUOT) or inside is not None
            error = _write_error(exc, path, f" ({inside})" if inside and inside != "." else "") if ours else None
            if error is None:
                raise
            raise error from exc
        check_destination(path, overwrite)
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
