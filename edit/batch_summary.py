"""The summary of a batch: DIR/batch_summary.json (every job's record) and
DIR/batch_summary.html (a row per edit: template | edit | target of its view, its numbers, links
to its outputs, or the error that stopped it; then every job)."""

from __future__ import annotations

import html
import os
from pathlib import Path

from render.io import write_json, write_text_atomic

JOB_KEYS = ("object", "stage", "edit", "status", "seconds", "message", "metrics")


def write_summary(out: Path, summary: dict) -> None:
    """Writes both files; `summary["jobs"]` holds the records of edit.batch_stages.run_job."""
    jobs = [{k: r.get(k) for k in JOB_KEYS} | {"job": r["job"]} for r in summary["jobs"]]
    counts = {s: sum(j["status"] == s for j in jobs) for s in ("done", "skipped", "failed")}
    write_json(out / "batch_summary.json", {**summary, "counts": counts, "jobs": jobs})
    write_text_atomic(out / "batch_summary.html", _html(out, summary, counts))


def summary_line(summary: dict) -> str:
    """`batch: 20 done, 3 skipped, 1 failed in 312 s -> DIR/batch_summary.html`."""
    jobs = summary["jobs"]
    counts = ", ".join(
        f"{sum(j['status'] == s for j in jobs)} {s}" for s in ("done", "skipped", "failed")
    )
    return f"batch: {counts} in {summary['seconds']:.0f} s -> {summary['out']}/batch_summary.html"


def _html(out: Path, summary: dict, counts: dict) -> str:
    records = summary["jobs"]
    edits = [r for r in records if r["stage"] == "edit"]
    rows = [_edit_row(out, r, records) for r in edits]
    jobs = [
        "<tr>"
        + "".join(
            f"<td>{html.escape(str(v))}</td>"
            for v in (r["job"], r["status"], f"{r['seconds']:.1f}", _numbers(r), r["message"])
        )
        + (
            f"<td><a href='{_link(out, Path(r['log']))}'>log</a></td>"
            if r.get("log")
            else "<td></td>"
        )
        + "</tr>"
        for r in records
    ]
    title = html.escape(f"sine batch {summary['batch']}")
    counted = ", ".join(f"{n} {s}" for s, n in counts.items())
    return "\n".join(
        [
            f"<!doctype html><html><head><meta charset='utf-8'><title>{title}</title>",
            "<style>body{font-family:sans-serif}td,th{border:1px solid #ccc;padding:4px;"
            "vertical-align:top}table{border-collapse:collapse}.failed{color:#b00}</style>",
            f"</head><body><h1>{title}</h1><p>{counted}; {summary['seconds']:.0f} s</p>",
            "<h2>Edits</h2><table><tr><th>object / edit</th>"
            "<th>template | edit | target (edited view)</th><th>numbers</th><th>outputs</th></tr>",
            *rows,
            "</table><h2>Jobs</h2><table><tr><th>job</th><th>status</th><th>seconds</th>"
            "<th>numbers</th><th>message</th><th>output</th></tr>",
            *jobs,
            "</table></body></html>\n",
        ]
    )


def _edit_row(out: Path, edit: dict, records: list[dict]) -> str:
    name = html.escape(f"{edit['object']} / {edit['edit']}")
    if edit["status"] == "failed":
        error = html.escape(edit["message"])
        return f"<tr><td>{name}</td><td colspan=3 class='failed'>failed: {error}</td></tr>"
    picture = Path(edit["result"]).parent / "edited_view.png"
    thumb = f"<img src='{_link(out, picture)}' width='480'>" if picture.is_file() else ""
    numbers, links = [_numbers(edit)], []
    for r in records:
        if r["object"] != edit["object"] or r["edit"] != edit["edit"] or r is edit:
            continue
        if r["status"] == "failed":
            links.append(f"<span class='failed'>{r['stage']}: {html.escape(r['message'])}</span>")
        elif r["stage"] == "eval":
            numbers.append("eval: " + _numbers(r))
            links.append(f"<a href='{_link(out, Path(r['result']))}'>eval.json</a>")
        else:
            links.append(f"<a href='{_link(out, Path(r['result']))}'>{Path(r['result']).name}</a>")
    return (
        f"<tr><td>{name}</td><td>{thumb}</td><td>{'<br>'.join(map(html.escape, numbers))}</td>"
        f"<td>{'<br>'.join(links)}</td></tr>"
    )


def _numbers(record: dict) -> str:
    return ", ".join(
        f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
        for k, v in record.get("metrics", {}).items()
        if k != "file"
    )


def _link(out: Path, path: Path) -> str:
    return html.escape(os.path.relpath(path, out))
