"""The demo report: one self-contained HTML page of sections with text, pictures and tables."""
from __future__ import annotations

import base64
import html
import re
from dataclasses import dataclass, field
from pathlib import Path

from skinsafe.core.skin.files import atomic_write


@dataclass
class Section:
    title: str
    text: str = ""  # paragraphs separated by blank lines
    images: list[tuple[str, str]] = field(default_factory=list)  # (PNG path, caption)
    tables: list[tuple[list[dict], str]] = field(default_factory=list)  # (rows, what the numbers mean)


def _table(rows: list[dict]) -> str:
    if not rows:
        return "<p><em>no rows</em></p>"
    keys = list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f"<th>{html.escape(str(k))}</th>" for k in keys)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(r.get(k, '')))}</td>" for k in keys) + "</tr>"
                   for r in rows)
    return f"<div class='scroll'><table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table></div>"


def _fmt(v) -> str:
    """Floats to 4 significant digits; from 10,000 up as whole numbers with thousands separators
    (3.288e+04 is hard to read in a table)."""
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:,.0f}" if abs(v) >= 1e4 and v == v and abs(v) != float("inf") else f"{v:.4g}"
    return str(v)


def _code(text: str) -> str:
    """`commands` in a paragraph as inline code."""
    return re.sub(r"`([^`]+)`", r"<code>\1</code>", text)


def _image(path: str, caption: str) -> str:
    p = Path(path)
    if not p.is_file():
        return f"<p><em>missing picture {html.escape(str(p))}</em></p>"
    data = base64.b64encode(p.read_bytes()).decode()
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


# pictures at their own size up to the page width (a 3-panel plot shrunk to half the page is
# unreadable); wide tables scroll inside the page instead of running off it
CSS = """body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
h1{border-bottom:2px solid #345}h2{margin-top:2em;color:#345}table{border-collapse:collapse;margin:.5em 0}
.scroll{overflow-x:auto;max-width:100%}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right;font-size:.9em;white-space:nowrap}
th{background:#eef;position:sticky;top:0}
figure{display:inline-block;vertical-align:top;margin:.5em;max-width:100%}img{max-width:100%;height:auto}
figcaption{font-size:.9em;color:#555}.meaning{font-size:.92em;color:#444;margin:0 0 1.2em}"""


def write_report(path: str | Path, title: str, intro: str, sections: list[Section]) -> Path:
    """Write the report (pictures embedded, so the one file can be mailed around)."""
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             f"<style>{CSS}</style></head><body><h1>{html.escape(title)}</h1><p>{html.escape(intro)}</p>"]
    for s in sections:
        parts.append(f"<h2>{html.escape(s.title)}</h2>")
        parts += [f"<p>{_code(html.escape(p))}</p>" for p in s.text.split("\n\n") if p.strip()]
        parts += [_image(p, c) for p, c in s.images]
        for rows, meaning in s.tables:
            parts.append(_table(rows))
            if meaning:
                parts.append(f"<p class='meaning'>{html.escape(meaning)}</p>")
    parts.append("</body></html>")
    return atomic_write(path, "\n".join(parts))
