"""HTML pieces of the static dashboard: the page shell with its navigation, tables, notes and plot slots.

Every page is self-contained except for ``assets/plotly.min.js`` (written once from the plotly wheel, so the
site works offline, from ``file://`` or any static server) and the videos under ``media/``.
"""
from __future__ import annotations

import html
from collections.abc import Sequence

PAGES = (("index.html", "Overview"), ("tables.html", "Paper tables"), ("curves.html", "Training curves"),
         ("claims.html", "Claims"), ("codebooks.html", "Codebooks"), ("quality.html", "Data quality"),
         ("videos.html", "Videos"), ("runs.html", "Runs"))

STYLE = """
body{font-family:system-ui,sans-serif;margin:0;color:#222}
nav{background:#1f3b57;padding:.6em 1.5em}nav a{color:#dfe9f3;margin-right:1.2em;text-decoration:none}
nav a.here{color:#fff;font-weight:600;border-bottom:2px solid #fff}
main{padding:1em 1.5em 3em}h2{margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.6em 0;font-size:13px}td,th{border:1px solid #ccc;padding:3px 8px}
th{background:#f1f4f7}td.num{text-align:right;font-variant-numeric:tabular-nums}
.pair{display:flex;gap:2em;flex-wrap:wrap;align-items:flex-start}.pair>div{min-width:0;max-width:100%;overflow-x:auto}
.note{color:#555;font-size:13px;max-width:70em}.empty{background:#fff8e1;border:1px solid #f0d890;padding:.8em}
figure{display:inline-block;margin:.5em 1em .5em 0}video{max-width:100%;background:#000}
code{background:#f3f3f3;padding:0 3px}.filters{margin:.6em 0}.filters input,.filters select{margin-right:1em}
"""


def esc(value: object) -> str:
    return html.escape(str(value))


def page(name: str, title: str, body: str, generated: str, plots: bool = False) -> str:
    """A whole page: navigation (``name`` highlighted), ``body`` and the plotly script when ``plots``."""
    nav = "".join(f'<a href="{href}"{" class=here" if href == name else ""}>{esc(label)}</a>' for href, label in PAGES)
    script = '<script src="assets/plotly.min.js"></script>' if plots else ""
    return (f"<!doctype html><html lang=en><head><meta charset=utf-8><title>{esc(title)} · M3T platform</title>"
            f"<style>{STYLE}</style>{script}</head><body><nav>{nav}</nav><main><h1>{esc(title)}</h1>{body}"
            f'<p class=note>Generated {esc(generated)} by <code>python -m dashboards.build</code>.</p></main></body></html>')


def _cell(value: object, tag: str = "td") -> str:
    text = str(value)
    numeric = tag == "td" and text.replace(".", "", 1).replace("-", "", 1).replace("%", "").strip().isdigit()
    return f"<{tag}{' class=num' if numeric else ''}>{esc(text)}</{tag}>"


def table(header: Sequence[object], rows: Sequence[Sequence[object]], table_id: str = "", caption: str = "") -> str:
    ident = f' id="{esc(table_id)}"' if table_id else ""
    cap = f"<caption>{esc(caption)}</caption>" if caption else ""
    head = "".join(_cell(h, "th") for h in header)
    body = "".join("<tr>" + "".join(_cell(c) for c in row) + "</tr>" for row in rows)
    return f"<table{ident}>{cap}<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def markdown(text: str, table_id: str = "") -> str:
    """The project's markdown tables (``m3t ...-table`` output: pipe tables, notes as lines or ``- `` items)
    as HTML; the table gets ``table_id``."""
    out, rows, items = [], [], []

    def flush_table() -> None:
        if rows:
            header, *body = rows
            out.append(table(header, body, table_id))
            rows.clear()

    def flush_items() -> None:
        if items:
            out.append("<ul class=note>" + "".join(f"<li>{esc(i)}</li>" for i in items) + "</ul>")
            items.clear()

    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("|"):
            flush_items()
            cells = [c.strip() for c in stripped.strip("|").split("|")]
            if not all(set(c) <= set("-: ") for c in cells):  # the |---| separator row
                rows.append(cells)
            continue
        flush_table()
        if stripped.startswith("- "):  # consecutive items make one list
            items.append(stripped[2:])
            continue
        flush_items()
        if stripped:
            out.append(f"<p class=note>{esc(stripped)}</p>")
    flush_table()
    flush_items()
    return "".join(out)


def empty(message: str) -> str:
    """What to run when a section has nothing to show yet."""
    return f"<div class=empty>{message}</div>"
