"""Small HTML pieces shared by the report's sections: formatted cells, tables, inline PNGs.

Every number cell carries ``data-key`` / ``data-value`` attributes with the raw JSON value, so a
test (or a script) can read the figures back from the page.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path
from typing import Any


def fmt(v: Any, digits: int = 2) -> str:
    """A value for a table cell: an en dash for None, yes/no, fixed digits for floats."""
    if v is None:
        return "&ndash;"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return html.escape(str(v))


def cell(key: str, v: Any, digits: int = 2, cls: str = "num") -> str:
    raw = "" if v is None else json.dumps(v)
    return (
        f'<td class="{cls}" data-key="{key}" data-value="{html.escape(raw, quote=True)}">'
        f"{fmt(v, digits)}</td>"
    )


def table(headers: list[str] | None, rows: list[list[str]], attrs: str = "") -> str:
    head = ""
    if headers:
        th = "".join(f"<th>{html.escape(h)}</th>" for h in headers)
        head = f"<thead><tr>{th}</tr></thead>"
    body = "".join("<tr>" + "".join(r) + "</tr>" for r in rows)
    return f"<table {attrs}>{head}<tbody>{body}</tbody></table>"


def td(v: Any, digits: int = 2, num: bool = False) -> str:
    return f'<td class="{"num" if num else ""}">{fmt(v, digits)}</td>'


def png_data_uri(path: Path) -> str:
    """A PNG file as a data URI (the page then needs no other file)."""
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")
