"""The one YAML reader of polarshape's files (run configurations, scenes, capture.yaml, capture
sessions, the capture.yaml that calibration updates).

It is ``yaml.safe_load`` except that a key given twice in one mapping is an error naming the file,
the key path and both lines: plain YAML keeps the last value silently, so a duplicated
``recovery:`` section would drop the first one without a word. YAML's merge key (``<<: *base``) may
still be overridden by an explicit key, as YAML intends.

Every problem (unreadable file, not UTF-8, not YAML, duplicate key) raises the error class the
caller names (:class:`~polarshape.errors.ConfigError` by default) with a one-line message.

Example:
    >>> load_yaml("run.yaml", text="a: 1\\na: 2\\n")
    Traceback (most recent call last):
    ...
    polarshape.errors.ConfigError: run.yaml: line 2: key 'a' appears twice (first on line 1); YAML would keep only the last value: remove one
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from pydantic import ValidationInfo

from polarshape.errors import ConfigError, PolarshapeError

__all__ = ["load_yaml", "resolve_config_path"]

_MERGE_TAG = "tag:yaml.org,2002:merge"


def _key_value(loader: yaml.SafeLoader, node: ScalarNode) -> Any:
    """The key as YAML reads it (so ``1`` and ``0x1``, or ``yes`` and ``true``, are the same key)."""
    try:
        value = loader.construct_object(node)
        hash(value)
    except (yaml.YAMLError, TypeError):
        return (node.tag, node.value)
    return value


def _find_duplicate(loader: yaml.SafeLoader, root: Node) -> tuple[str, int, int] | None:
    """(key path, line, first line) of the first key given twice in one mapping, lines from 1."""
    seen_nodes: set[int] = set()
    stack: list[tuple[Node, str]] = [(root, "")]
    while stack:
        node, path = stack.pop()
        if id(node) in seen_nodes:  # an alias: checked where its anchor is
            continue
        seen_nodes.add(id(node))
        if isinstance(node, MappingNode):
            first_line: dict[Any, int] = {}
            children: list[tuple[Node, str]] = []
            for key_node, value_node in node.value:
                if key_node.tag == _MERGE_TAG:
                    continue
                if isinstance(key_node, ScalarNode):
                    key = _key_value(loader, key_node)
                    name = f"{path}.{key_node.value}" if path else str(key_node.value)
                    line = key_node.start_mark.line + 1
                    if key in first_line:
                        return name, line, first_line[key]
                    first_line[key] = line
                else:
                    name = f"{path}.?" if path else "?"
                children.append((value_node, name))
            stack.extend(reversed(children))  # popped in document order
        elif isinstance(node, SequenceNode):
            stack.extend((item, f"{path}[{i}]") for i, item in reversed(list(enumerate(node.value))))
    return None


def _one_line(err: yaml.YAMLError) -> str:
    """A YAML parser error on one line: ``line 3, column 7: could not find expected ':'``."""
    mark = getattr(err, "problem_mark", None)
    problem = getattr(err, "problem", None) or str(err)
    context = getattr(err, "context", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    text = f"{where}{problem}" + (f" ({context})" if context else "")
    return " ".join(text.split())


def load_yaml(
    path: str | os.PathLike[str],
    *,
    text: str | None = None,
    error: type[PolarshapeError] = ConfigError,
) -> Any:
    """Read one YAML document like ``yaml.safe_load``, refusing duplicate keys.

    Args:
        path: the file (read as UTF-8 unless ``text`` is given); named in every message.
        text: the file's content, when the caller has already read it.
        error: the error class to raise (e.g. :class:`~polarshape.errors.CaptureError` for capture.yaml).

    Returns:
        The parsed document (None for an empty file).

    Raises:
        ``error``: ``<path>: cannot read it: <reason>``, ``<path>: not UTF-8 text: …``,
            ``<path>: not valid YAML: line L, column C: …``, or ``<path>: line L: key 'a.b' appears
            twice (first on line M); …``.
    """
    path = Path(path)
    if text is None:
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as err:
            raise error(f"{path}: not UTF-8 text: {err}") from None
        except OSError as err:
            raise error(f"{path}: cannot read it: {err.strerror or err}") from None
    loader = yaml.SafeLoader(text)
    try:
        root = loader.get_single_node()
        if root is None:
            return None
        duplicate = _find_duplicate(loader, root)
        if duplicate is not None:
            key, line, first = duplicate
            raise error(
                f"{path}: line {line}: key {key!r} appears twice (first on line {first}); YAML would keep only "
                "the last value: remove one"
            )
        return loader.construct_document(root)
    except yaml.YAMLError as err:
        raise error(f"{path}: not valid YAML: {_one_line(err)}") from None
    finally:
        loader.dispose()


def resolve_config_path(value: str | None, info: ValidationInfo) -> str | None:
    """A pydantic validator's path made absolute against the configuration file's folder (the
    validation context's ``base_dir``; the working directory without one). None stays None.

    Raises:
        ValueError: an empty path (pydantic reports it under the key).
    """
    if value is None:
        return None
    if not value.strip():
        raise ValueError("must be a non-empty path")
    path = Path(value).expanduser()
    base = (info.context or {}).get("base_dir")
    if not path.is_absolute() and base is not None:
        path = Path(base) / path
    return str(path)
