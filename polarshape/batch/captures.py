"""The captures of a batch: folders and glob patterns from the command line → named capture folders.

Each capture is named by its folder (``captures/ball`` → ``ball``); its result goes to ``DIR/<name>``.
"""

from __future__ import annotations

import glob
from collections.abc import Sequence
from pathlib import Path

from polarshape.errors import CaptureError

__all__ = ["BATCH_FILES", "find_captures"]

#: The batch folder's own files: no capture may be named like one of them.
BATCH_FILES: tuple[str, ...] = ("batch.json", "summary.csv", "index.html", "failed.json")

_GLOB_CHARS = frozenset("*?[")


def _matches(pattern: str) -> list[Path]:
    """The folders ``pattern`` names: a glob's matching folders (sorted; files are ignored, except a
    ``capture.yaml``, which names its folder), or the one folder of a plain path."""
    if _GLOB_CHARS & set(pattern):
        found = []
        for match in sorted(glob.glob(pattern)):
            path = Path(match)
            if path.is_dir():
                found.append(path)
            elif path.name == "capture.yaml":
                found.append(path.parent)
        if not found:
            raise CaptureError(f"CAPTURES: {pattern!r} matches no folder; give capture folders (holding "
                               "capture.yaml) or a pattern that matches some, e.g. 'captures/*'")
        return found
    path = Path(pattern)
    if path.name == "capture.yaml" and path.is_file():
        return [path.parent]
    if not path.is_dir():
        raise CaptureError(f"CAPTURES: {pattern} is not a folder; give capture folders (holding capture.yaml) "
                           "or glob patterns")
    return [path]


def find_captures(patterns: Sequence[str]) -> dict[str, Path]:
    """Capture name → absolute capture folder, in the order given, each folder once.

    A pattern holding ``*``, ``?`` or ``[`` is a glob (its matching folders, sorted); anything else
    must be a folder. A folder is taken whether or not it holds a valid capture: one that does not
    fails on its own in the batch (recorded in ``failed.json``), without stopping the others.

    Raises:
        CaptureError: a path that is not a folder, a pattern matching no folder, no pattern at all,
            two folders with the same name (their results would collide), or a name of the batch
            folder's own files (:data:`BATCH_FILES`).

    Example:
        >>> find_captures(["captures/*", "more/ball"])  # doctest: +SKIP
        {'bust': PosixPath('/data/captures/bust'), 'cup': ..., 'ball': PosixPath('/data/more/ball')}
    """
    if not patterns:
        raise CaptureError("CAPTURES: no capture given; name capture folders or glob patterns (e.g. 'captures/*')")
    named: dict[str, Path] = {}
    for pattern in patterns:
        for folder in _matches(pattern):
            folder = folder.absolute()
            name = folder.resolve().name
            if name in BATCH_FILES or name.startswith("."):
                raise CaptureError(f"CAPTURES: {folder}: a capture may not be named {name!r} (the batch folder's "
                                   "own files, or a hidden name); rename the folder")
            other = named.get(name)
            if other is not None and other.resolve() != folder.resolve():
                raise CaptureError(f"CAPTURES: two captures are named {name!r} ({other} and {folder}): their results "
                                   f"would both be DIR/{name}; rename one folder or run them in separate batches")
            named.setdefault(name, folder)
    return named
