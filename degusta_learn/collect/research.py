"""The researcher's side of a study: who has finished (an HTML page, every value escaped) and the data as a zip.

The export holds the dataset files as `degusta data validate` reads them (catalog, tables, meta, arrangements,
ratings; pictures the catalog and tables name) and the study's own record (collect/self_evaluation.jsonl), never the
participants' session states. `complete=True` keeps only the participants who finished every table (the paper
kept only those who completed all five trials and the self-evaluation).
"""

from __future__ import annotations

import html
import io
import json
import time
import zipfile
from urllib.parse import urlencode
from pathlib import Path

from degusta_learn.collect.store import StudyStore
from degusta_learn.collect.study import Study

DATASET_FILES = ("catalog.json", "tables.json", "meta.json")
LOGS = ("arrangements.jsonl", "ratings.jsonl", "collect/self_evaluation.jsonl")


def _when(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(t)) if t else "-"


def progress_page(study: Study, rows: list[dict], key: str) -> str:
    """The progress table as a small, self-contained HTML page (no script; every value escaped)."""
    e = html.escape
    query = urlencode({"key": key})
    done = sum(r["finished"] for r in rows)
    body = "\n".join(
        f"<tr><td>{e(r['participant'])}</td><td>{r['tables_done']} of {r['tables']}</td><td>{e(r['stage'])}</td>"
        f"<td>{'yes' if r['finished'] else 'no'}</td><td>{e(_when(r['started']))}</td><td>{e(_when(r['updated']))}</td></tr>"
        for r in rows) or '<tr><td colspan="6">nobody has started yet</td></tr>'
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{e(study.config.title)}: progress</title>
<link rel="stylesheet" href="/static/app.css"></head>
<body class="research"><main>
<h1>{e(study.config.title)}: progress</h1>
<p>Study folder <code>{e(str(study.root))}</code>: {len(rows)} participants started, {done} finished;
{study.config.tables_per_participant} tables each, at least {study.min_objects} objects per table.</p>
<table><thead><tr><th>participant</th><th>tables done</th><th>step</th><th>finished</th><th>started</th>
<th>last change</th></tr></thead>
<tbody>
{body}
</tbody></table>
<p>Download the data (a zip of the dataset files): <a href="/research/export?{e(query)}">every participant</a> ·
<a href="/research/export?{e(query)}&amp;complete=1">only those who finished every table</a>.</p>
</main></body></html>
"""


def _filtered(path: Path, keep: set[str] | None) -> bytes:
    if not path.exists():
        return b""
    data = path.read_bytes()
    if keep is None:
        return data
    lines = [line for line in data.splitlines(keepends=True) if line.strip()
             and str(json.loads(line)["participant"]) in keep]
    return b"".join(lines)


def export_zip(study: Study, store: StudyStore, complete: bool = False) -> bytes:
    """The study's data as a zip (module docstring)."""
    keep = store.finished() if complete else None
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name in DATASET_FILES:
            if (study.root / name).exists():
                z.writestr(name, (study.root / name).read_bytes())
        with store.writing():
            for name in LOGS:
                data = _filtered(study.root / name, keep)
                if data:
                    z.writestr(name, data)
        pictures = {o.image for o in study.catalog.objects if o.image} | {t.image for t in study.tables.values()
                                                                          if t.image}
        for rel in sorted(pictures):
            z.writestr(rel, (study.root / rel).read_bytes())
    return buf.getvalue()


__all__ = ["export_zip", "progress_page"]
