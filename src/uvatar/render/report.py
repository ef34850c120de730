"""Self-contained HTML reports: title, sections of text, metric tables, images and videos.

Media are referenced by path relative to the report (not embedded), so the folder can be zipped and
opened anywhere. No JavaScript or external CSS.
"""

from __future__ import annotations

import html
import os
from pathlib import Path

from uvatar.io_utils import atomic_path

__all__ = ["html_report", "table_figure"]

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1100px;
margin:2em auto;padding:0 1em;color:#222;line-height:1.45}
h1{border-bottom:2px solid #ddd;padding-bottom:.3em} h2{margin-top:1.8em;color:#333}
.wide{max-width:100%;overflow-x:auto} table{border-collapse:collapse;margin:.8em 0} th,td{border:1px solid #ccc;padding:.3em .7em;
text-align:right} th{background:#f3f3f3} td:first-child,th:first-child{text-align:left}
figure{display:inline-block;margin:.4em;vertical-align:top} figcaption{font-size:.85em;color:#555;
text-align:center} img,video{max-width:100%;border:1px solid #ddd}
.meta{color:#777;font-size:.85em} pre{background:#f6f6f6;padding:.6em;overflow-x:auto;white-space:pre-wrap}
"""


def table_figure(metrics: dict, *keys: str):
    """A table cell of a metrics dict: the first of ``keys`` that holds a finite number, rounded to 4
    decimals, or "" where none does (absent, or NaN: e.g. a mask with no interior)."""
    import math

    for key in keys:
        value = metrics.get(key)
        if isinstance(value, int | float) and math.isfinite(value):
            return round(float(value), 4)
    return ""


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def _table(table) -> str:
    """table: {"columns": [...], "rows": [[...], ...]} or a list of dicts (keys = columns)."""
    if isinstance(table, dict) and "rows" in table:
        columns, rows = list(table.get("columns", [])), table["rows"]
    else:
        rows_d = list(table)
        columns = list(dict.fromkeys(k for r in rows_d for k in r))
        rows = [[r.get(c, "") for c in columns] for r in rows_d]
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(v)}</td>" for v in row) + "</tr>" for row in rows)
    return f'<div class="wide"><table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table></div>'


def _media(items, root: Path, kind: str) -> str:
    out = []
    for item in items:
        src, caption = (item, "") if isinstance(item, str | Path) else (item[0], item[1])
        p = Path(src)
        rel = os.path.relpath(p.resolve(), root)  # as the program sees it -> relative to the report's folder
        rel = html.escape(Path(rel).as_posix(), quote=True)
        tag = (f'<img src="{rel}" alt="{html.escape(caption or p.name)}" loading="lazy">' if kind == "img"
               else f'<video src="{rel}" controls loop muted playsinline></video>')
        cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
        out.append(f"<figure>{tag}{cap}</figure>")
    return "<div>" + "".join(out) + "</div>"


def html_report(path, title: str, sections, subtitle: str | None = None) -> Path:
    """Write an HTML report to ``path`` (atomic) and return the path.

    sections: list of dicts with optional keys ``title``, ``text`` (str, paragraphs split on blank
    lines), ``pre`` (preformatted text), ``table`` (see :func:`_table`) or ``tables`` (list),
    ``images`` and ``videos`` (lists of paths or (path, caption): absolute, or relative to the
    working directory like every other path; the report links them relative to its own folder, so
    it opens from anywhere and the folder can be moved or zipped).
    """
    path = Path(path)
    root = path.parent.resolve()
    parts = [f"<h1>{html.escape(title)}</h1>"]
    if subtitle:
        parts.append(f'<p class="meta">{html.escape(subtitle)}</p>')
    for sec in sections:
        if sec.get("title"):
            parts.append(f"<h2>{html.escape(sec['title'])}</h2>")
        for para in str(sec.get("text", "")).split("\n\n"):
            if para.strip():
                parts.append(f"<p>{html.escape(para.strip())}</p>")
        if sec.get("pre"):
            parts.append(f"<pre>{html.escape(str(sec['pre']))}</pre>")
        tables = list(sec.get("tables", [])) + ([sec["table"]] if sec.get("table") is not None else [])
        parts.extend(_table(t) for t in tables)
        if sec.get("images"):
            parts.append(_media(sec["images"], root, "img"))
        if sec.get("videos"):
            parts.append(_media(sec["videos"], root, "video"))
    doc = (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
           f'<meta name="viewport" content="width=device-width, initial-scale=1">'
           f"<title>{html.escape(title)}</title><style>{_CSS}</style></head>\n<body>\n"
           + "\n".join(parts) + "\n</body></html>\n")
    with atomic_path(path) as tmp:
        tmp.write_text(doc, encoding="utf-8")
    return path
