"""The batch folder's tables: ``summary.csv`` and ``index.html`` (one row per capture) and ``failed.json``.

All three are rewritten atomically after every capture that finishes, so a batch killed at any
moment leaves them consistent with the result folders beside them.
"""

from __future__ import annotations

import csv
import html
import io
import json
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from polarshape.io.atomic import atomic_write_text

__all__ = ["FAILED_FORMAT", "STATUSES", "SUMMARY_COLUMNS", "read_failed", "summary_row", "write_failed",
           "write_summary"]

#: Format tag of failed.json.
FAILED_FORMAT = "polarshape-batch-failed/1"

#: A capture's status in the summary: run by this batch, complete from an earlier run (skipped),
#: failed, or not run (yet: the batch is running, or it was interrupted).
STATUSES: tuple[str, ...] = ("done", "complete", "failed", "pending")

#: Columns of summary.csv, in order (index.html shows the same).
SUMMARY_COLUMNS: tuple[str, ...] = (
    "capture",              # the capture's name (its result folder is DIR/<capture>)
    "status",               # one of STATUSES
    "model",                # the model the run fitted (fmbrdf, lambertian)
    "materials",            # materials fitted (one per run today)
    "ior",                  # FMBRDF refractive index mu
    "alpha",                # FMBRDF roughness alpha
    "normal_mean_deg",      # mean angular error of the normals vs ground truth (when the capture has it)
    "normal_median_deg",
    "heldout_s0_rel_rmse",  # held-out-light relative RMSE of s0, the run's model (params.json validation)
    "warnings",             # how many warnings the run recorded
    "warning_list",         # their texts, "; "-separated
    "time_s",               # pipeline time (failed: the worker's time until the failure)
    "result",               # the result folder, relative to DIR
    "report",               # its report, relative to DIR
    "error",                # failed: "<Kind>: <message>"
    "source",               # the capture folder
)


def _warnings(params: Mapping[str, Any]) -> list[str]:
    """The run's warnings: params.json ``warnings`` (``"Kind: message"``) and the self-checks'
    ``checks.warnings`` (``{"name", "message"}``), each text once."""
    texts = [str(w) for w in params.get("warnings") or []]
    checks = params.get("checks")
    for item in (checks.get("warnings") or []) if isinstance(checks, Mapping) else []:
        if isinstance(item, Mapping):
            texts.append(f"{item.get('name', 'warning')}: {item.get('message', '')}")
    return list(dict.fromkeys(texts))


def _heldout(params: Mapping[str, Any]) -> float | None:
    """The held-out-light s0 relative RMSE of the run's own model, when the run validated it."""
    validation = params.get("validation")
    models = validation.get("models") if isinstance(validation, Mapping) else None
    record = models.get(params.get("model")) if isinstance(models, Mapping) else None
    value = record.get("s0_rel_rmse") if isinstance(record, Mapping) else None
    return float(value) if isinstance(value, (int, float)) else None


def summary_row(name: str, source: str | os.PathLike[str], status: str, params: Mapping[str, Any] | None = None,
                *, error: Mapping[str, Any] | None = None, seconds: float | None = None) -> dict[str, Any]:
    """One row of summary.csv (keys :data:`SUMMARY_COLUMNS`; None = empty cell).

    Args:
        name: the capture's name. source: its folder. status: one of :data:`STATUSES`.
        params: the result's params.json content (done/complete), read with ``.get``: a section the
            run did not write (no ground truth, no validation) leaves its cells empty.
        error: failed: the worker's error record (``type``, ``message``). seconds: failed: time spent.
    """
    if status not in STATUSES:
        raise ValueError(f"status must be one of {STATUSES}; got {status!r}")
    row: dict[str, Any] = dict.fromkeys(SUMMARY_COLUMNS)
    row.update(capture=name, status=status, source=str(source))
    if error is not None:
        row["error"] = f"{error.get('type', 'Error')}: {error.get('message', '')}"
        row["time_s"] = seconds
    if params is None:
        return row
    material = params.get("params") or {}
    normals = (params.get("metrics") or {}).get("normals") or {}
    warned = _warnings(params)
    reports = [str(f) for f in params.get("report") or []]
    row.update(
        model=params.get("model"), materials=1, ior=material.get("ior"), alpha=material.get("alpha"),
        normal_mean_deg=normals.get("mean_deg"), normal_median_deg=normals.get("median_deg"),
        heldout_s0_rel_rmse=_heldout(params), warnings=len(warned), warning_list="; ".join(warned),
        time_s=(params.get("timings_s") or {}).get("total"), result=name,
        report=next((f"{name}/{f}" for f in reports if f.endswith(".html")),
                    f"{name}/{reports[0]}" if reports else None),
    )
    return row


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _html(rows: Sequence[Mapping[str, Any]], title: str) -> str:
    counts = {s: sum(r["status"] == s for r in rows) for s in STATUSES}
    head = "".join(f"<th>{html.escape(c)}</th>" for c in SUMMARY_COLUMNS if c != "source")
    body = []
    for row in rows:
        cells = []
        for column in SUMMARY_COLUMNS:
            if column == "source":
                continue
            text = html.escape(_cell(row[column]))
            if column in ("result", "report") and row[column]:
                text = f'<a href="{html.escape(str(row[column]), quote=True)}">{text}</a>'
            elif column == "capture":
                text = f'<span title="{html.escape(str(row["source"]), quote=True)}">{text}</span>'
            cells.append(f"<td>{text}</td>")
        body.append(f'<tr class="{html.escape(str(row["status"]))}">{"".join(cells)}</tr>')
    summary = ", ".join(f"{n} {s}" for s, n in counts.items() if n)
    return (
        "<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>" + html.escape(title) + "</title>\n"
        "<style>body{font-family:sans-serif}table{border-collapse:collapse;font-size:13px}"
        "td,th{border:1px solid #ccc;padding:3px 6px;text-align:left}tr.failed{background:#fdd}"
        "tr.pending{color:#888}</style></head><body>\n"
        f"<h1>{html.escape(title)}</h1>\n<p>{len(rows)} captures: {html.escape(summary)}; "
        "the same table as <a href=\"summary.csv\">summary.csv</a>; failures in "
        "<a href=\"failed.json\">failed.json</a>.</p>\n"
        f"<table><tr>{head}</tr>\n" + "\n".join(body) + "\n</table></body></html>\n"
    )


def write_summary(folder: Path, rows: Sequence[Mapping[str, Any]], *, title: str = "polarshape batch") -> None:
    """Write ``folder/summary.csv`` and ``folder/index.html`` (links to every result and report) atomically."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(SUMMARY_COLUMNS)
    writer.writerows([_cell(row[c]) for c in SUMMARY_COLUMNS] for row in rows)
    atomic_write_text(folder / "summary.csv", buffer.getvalue(), overwrite=True)
    atomic_write_text(folder / "index.html", _html(rows, title), overwrite=True)


def write_failed(folder: Path, failures: Mapping[str, Mapping[str, Any]]) -> None:
    """Write ``folder/failed.json`` atomically: ``{"format", "failed": [{"capture", "source", "type",
    "message", "exit_status", ...}, ...]}`` in the order given (empty list when none failed)."""
    entries = [{"capture": name, **record} for name, record in failures.items()]
    text = json.dumps({"format": FAILED_FORMAT, "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "failed": entries},
                      indent=1, default=str)
    atomic_write_text(folder / "failed.json", text + "\n", overwrite=True)


def read_failed(folder: Path) -> dict[str, dict[str, Any]]:
    """The failures an earlier batch recorded in ``folder/failed.json`` (name → record); empty when
    there is none or it cannot be read."""
    try:
        data = json.loads((folder / "failed.json").read_text())
        return {str(e["capture"]): {k: v for k, v in e.items() if k != "capture"} for e in data["failed"]}
    except (OSError, ValueError, KeyError, TypeError):
        return {}
