"""Where an importer may write its capture: never over, or around, what it reads."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from polarshape.errors import OutputExistsError

__all__ = ["check_import_destination"]


def check_import_destination(sources: Iterable[Path], out: Path, *, overwrite: bool) -> None:
    """Refuse ``out`` when it is, or holds, one of ``sources`` (folders or files the import reads),
    or when it exists and ``overwrite`` is False; the write itself then replaces only a previous
    capture (:func:`polarshape.io.capture.write_capture`).

    Raises:
        OutputExistsError: naming the source or the existing folder, and the fix (exit status 1).
    """
    o = out.resolve()
    for src in sources:
        s = src.resolve()
        if o == s or o in s.parents:
            kind = "folder" if s.is_dir() else "file"
            raise OutputExistsError(f"{out}: is, or holds, the source {kind} {src}; refusing to write the capture "
                                    "there (choose another --out)")
    if out.exists() and not overwrite:
        raise OutputExistsError(f"{out} already exists; refusing to overwrite it (pass --overwrite or another --out)")
