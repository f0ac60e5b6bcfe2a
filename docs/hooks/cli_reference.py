"""mkdocs hook: the CLI reference page, rendered from the ``counterscene`` argument parser.

``docs/cli.md`` holds the marker :data:`MARKER`; at build time (``hooks:`` in mkdocs.yml)
:func:`on_page_markdown` replaces it with :func:`render`: every subcommand of
``counterscene_env.cli._parser()``, its usage, description and arguments. The page therefore
always says what the installed command accepts. :func:`render` needs only the package, not
mkdocs (``tests/test_docs.py`` calls it).
"""

from __future__ import annotations

import argparse
import html
import re

#: The line of docs/cli.md that the reference replaces.
MARKER = "<!-- cli-reference -->"
#: Characters per line of the usage blocks (argparse wraps at this width).
WIDTH = 72


def on_page_markdown(markdown: str, page, config, files, **kwargs) -> str:
    """mkdocs event: render the reference into the page that carries the marker."""
    if MARKER not in markdown:
        return markdown
    return markdown.replace(MARKER, render())


def render() -> str:
    """The reference as Markdown (with HTML tables): an index of the subcommands, then one
    section per subcommand."""
    from counterscene_env.cli import _parser

    parser = _parser()
    parser.formatter_class = lambda prog: argparse.HelpFormatter(prog, width=WIDTH)
    commands = subcommands(parser)
    index = [f"```text\n{parser.format_usage().strip()}\n```", ""]
    index += ["| command | what it does |", "|---|---|"]
    index += [f"| [`{name}`](#{anchor(name)}) | {inline(about)} |" for name, about, _ in commands]
    parts = ["\n".join(index)]
    parts += [section(name, about, sub) for name, about, sub in commands]
    return "\n\n".join(parts) + "\n"


def subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """``(name, one-line help, parser)`` of every subcommand, in the parser's order."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            about = {a.dest: a.help or "" for a in action._choices_actions}
            return [(name, about.get(name, ""), sub) for name, sub in action.choices.items()]
    raise ValueError(f"{parser.prog} has no subcommands")


def anchor(name: str) -> str:
    """The heading id Python-Markdown's toc gives ``counterscene NAME``."""
    return "counterscene-" + name


def section(name: str, about: str, parser: argparse.ArgumentParser) -> str:
    """One subcommand: heading, one-line help, usage, description, one table per group."""
    cls = parser.formatter_class
    parser.formatter_class = lambda prog: cls(prog, width=WIDTH)
    usage = parser.format_usage().strip()
    formatter = parser._get_formatter()
    out = [f"## `counterscene {name}` {{#{anchor(name)}}}", inline(about)]
    out.append(f"```text\n{usage}\n```")
    if parser.description:
        out.append(inline(" ".join(parser.description.split())))
    for group in parser._mutually_exclusive_groups:
        if group.required:
            flags = ", ".join(f"`{a.option_strings[0]}`" for a in group._group_actions)
            out.append(f"Exactly one of {flags} is required.")
    for group in parser._action_groups:
        actions = [a for a in group._group_actions if shown(a)]
        if not actions:
            continue
        out.append(f"**{inline(group.title or 'arguments')}**")
        out.append(table(actions, formatter))
    parser.formatter_class = cls
    return "\n\n".join(out)


def shown(action: argparse.Action) -> bool:
    """Every argument but ``-h, --help`` (which every command has) and hidden ones."""
    return action.help is not argparse.SUPPRESS and not isinstance(action, argparse._HelpAction)


def table(actions: list[argparse.Action], formatter: argparse.HelpFormatter) -> str:
    """An HTML table of ``actions``: the argument as typed, and its help text."""
    rows = []
    for action in actions:
        invocation = html.escape(formatter._format_action_invocation(action), quote=False)
        required = " <em>(required)</em>" if action.required and action.option_strings else ""
        text = formatter._expand_help(action) if action.help else ""
        rows.append(
            f"<tr><td><code>{invocation}</code>{required}</td><td>{inline_html(text)}</td></tr>"
        )
    head = "<table>\n<thead><tr><th>argument</th><th>meaning</th></tr></thead>\n<tbody>"
    return "\n".join([head, *rows, "</tbody>\n</table>"])


_CODE = re.compile(r"``?([^`]+?)``?")


def inline_html(text: str) -> str:
    """Help text as HTML: escaped, with ``code`` and `code` spans as <code>."""
    return _CODE.sub(r"<code>\1</code>", html.escape(" ".join(text.split()), quote=False))


def inline(text: str) -> str:
    """Help text as Markdown: the same, safe inside a Markdown table or paragraph."""
    return inline_html(text).replace("|", "&#124;")
