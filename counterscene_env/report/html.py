"""A report document (``report.document``) as one self-contained HTML page: figures are
embedded as base64 ``data:`` URIs and the style is inline, so the page opens offline and
keeps working when copied alone. No script, no web font, no remote address. Videos are
linked (and shown) from ``videos/`` beside the page: they would multiply its size.
"""

from __future__ import annotations

import base64
from collections.abc import Sequence
from html import escape
from pathlib import Path

from counterscene_env.report.document import (
    Block,
    Bullets,
    Cell,
    Figure,
    Heading,
    Link,
    Paragraph,
    Table,
    Video,
)

_STYLE = """
body { font: 15px/1.45 system-ui, sans-serif; max-width: 60rem; margin: 2rem auto;
       padding: 0 1rem; color: #222; }
h1, h2, h3 { line-height: 1.2; }
table { border-collapse: collapse; margin: 1rem 0; font-size: 14px; }
th, td { border: 1px solid #ccc; padding: 0.25rem 0.6rem; text-align: left; }
th { background: #f0f0f0; }
tr:nth-child(even) td { background: #fafafa; }
figure { margin: 1.5rem 0; }
figure img, figure video { max-width: 100%; border: 1px solid #ddd; }
figcaption { color: #555; font-size: 13px; }
"""


def _cell(cell: Cell) -> str:
    if isinstance(cell, Link):
        return f'<a href="{escape(cell.href)}">{escape(cell.text)}</a>'
    return escape(cell)


def _data_uri(path: Path, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _block(block: Block, root: Path) -> str:
    if isinstance(block, Heading):
        level = min(max(block.level, 1), 6)
        return f"<h{level}>{escape(block.text)}</h{level}>"
    if isinstance(block, Paragraph):
        return f"<p>{escape(block.text)}</p>"
    if isinstance(block, Bullets):
        return "<ul>" + "".join(f"<li>{escape(i)}</li>" for i in block.items) + "</ul>"
    if isinstance(block, Table):
        head = "".join(f"<th>{escape(h)}</th>" for h in block.header)
        body = "".join(
            "<tr>" + "".join(f"<td>{_cell(c)}</td>" for c in row) + "</tr>" for row in block.rows
        )
        return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"
    if isinstance(block, Figure):
        uri = _data_uri(root / block.path, "image/png")
        return (
            f'<figure><img src="{uri}" alt="{escape(block.caption)}">'
            f"<figcaption>{escape(block.caption)}</figcaption></figure>"
        )
    if isinstance(block, Video):
        return _video(block)
    raise TypeError(f"not a report block: {type(block).__name__}")


def _video(block: Video) -> str:
    """The MP4 in a ``<video>`` element (the GIF where there is no MP4), with links to both."""
    links = " · ".join(
        f'<a href="{escape(p.as_posix())}">{kind}</a>'
        for kind, p in (("MP4", block.mp4), ("GIF", block.gif))
        if p
    )
    if block.mp4:
        player = f'<video controls loop muted src="{escape(block.mp4.as_posix())}"></video>'
    elif block.gif:
        player = f'<img src="{escape(block.gif.as_posix())}" alt="{escape(block.caption)}">'
    else:
        player = ""
    return f"<figure>{player}<figcaption>{escape(block.caption)} ({links})</figcaption></figure>"


def render(blocks: Sequence[Block], root: Path, title: str) -> str:
    """The document as an HTML page; ``root`` is the directory the figures' paths are
    relative to (their bytes are embedded)."""
    body = "\n".join(_block(b, root) for b in blocks)
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{escape(title)}</title>\n<style>{_STYLE}</style>\n</head>\n"
        f"<body>\n{body}\n</body>\n</html>\n"
    )
