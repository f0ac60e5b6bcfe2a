"""A report document (``report.document``) as Markdown: figures and videos as links to the
files beside it (``plots/``, ``videos/``)."""

from __future__ import annotations

from collections.abc import Sequence

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


def _escape(text: str) -> str:
    return text.replace("|", "\\|")


def _cell(cell: Cell) -> str:
    if isinstance(cell, Link):
        return f"[{_escape(cell.text)}]({cell.href})"
    return _escape(cell)


def _block(block: Block) -> str:
    if isinstance(block, Heading):
        return f"{'#' * block.level} {block.text}"
    if isinstance(block, Paragraph):
        return block.text
    if isinstance(block, Bullets):
        return "\n".join(f"- {item}" for item in block.items)
    if isinstance(block, Table):
        lines = [
            "| " + " | ".join(map(_escape, block.header)) + " |",
            "|" + "---|" * len(block.header),
        ]
        lines += ["| " + " | ".join(map(_cell, row)) + " |" for row in block.rows]
        return "\n".join(lines)
    if isinstance(block, Figure):
        return f"![{block.caption}]({block.path.as_posix()})\n\n*{block.caption}*"
    if isinstance(block, Video):
        links = [f"[{k}]({p.as_posix()})" for k, p in (("MP4", block.mp4), ("GIF", block.gif)) if p]
        return f"{block.caption} ({', '.join(links)})"
    raise TypeError(f"not a report block: {type(block).__name__}")


def render(blocks: Sequence[Block]) -> str:
    """The document as Markdown text."""
    return "\n\n".join(_block(b) for b in blocks) + "\n"
