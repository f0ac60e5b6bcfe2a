"""The documentation site's own code: the CLI reference hook and the nav (no mkdocs needed)."""

from __future__ import annotations

import argparse
import importlib.util
import re
import runpy
from pathlib import Path

import pytest

from counterscene_env.cli import _parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _hook():
    path = DOCS / "hooks" / "cli_reference.py"
    spec = importlib.util.spec_from_file_location("cli_reference", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in _parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_the_cli_reference_renders_every_subcommand_and_every_flag():
    text = _hook().render()
    subs = _subparsers()
    assert subs, "the parser has no subcommands"
    for name, sub in subs.items():
        assert f"## `counterscene {name}` {{#counterscene-{name}}}" in text
        assert f"usage: counterscene {name}" in text
        for action in sub._actions:
            for flag in action.option_strings:
                if flag not in ("-h", "--help"):
                    assert flag in text, f"{name}: {flag} missing from the reference"


def test_the_hook_fills_only_the_page_with_the_marker():
    hook = _hook()
    assert hook.MARKER in (DOCS / "cli.md").read_text()
    page = hook.on_page_markdown(f"# CLI\n\n{hook.MARKER}\n", page=None, config=None, files=None)
    assert hook.MARKER not in page and "counterscene stress" in page
    assert hook.on_page_markdown("# other\n", page=None, config=None, files=None) == "# other\n"


def test_every_docs_page_is_in_the_nav():
    nav = (ROOT / "mkdocs.yml").read_text()
    listed = set(re.findall(r":\s*([\w/]+\.md)\s*$", nav, flags=re.MULTILINE))
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")}
    assert pages - listed == set(), "pages missing from the nav in mkdocs.yml"


def _tool_help(path: Path, capsys, monkeypatch) -> str:
    """What ``python tools/NAME.py --help`` prints, run in this process."""
    monkeypatch.setattr("sys.argv", [str(path), "--help"])
    with pytest.raises(SystemExit) as exit_:
        runpy.run_path(str(path), run_name="__main__")
    assert exit_.value.code == 0, f"{path.name} --help failed"
    return capsys.readouterr().out


def test_every_tool_command_the_docs_cite_exists_and_takes_its_flags(capsys, monkeypatch):
    """The measurements in docs/ and the README cite ``python tools/NAME.py ... --flag``:
    each such tool runs, and each flag cited for it is one it takes."""
    cited: dict[str, set[str]] = {}
    pages = [ROOT / "README.md", *DOCS.rglob("*.md")]
    for page in pages:
        for name, rest in re.findall(r"python tools/(\w+)\.py([^`\n]*)", page.read_text()):
            cited.setdefault(name, set()).update(re.findall(r"(?<![\w-])--[a-z][\w-]*", rest))
    assert cited, "no tool command found in the docs"
    for name, flags in sorted(cited.items()):
        path = ROOT / "tools" / f"{name}.py"
        assert path.exists(), f"the docs cite tools/{name}.py, which does not exist"
        text = _tool_help(path, capsys, monkeypatch)
        missing = sorted(f for f in flags if f not in text)
        assert not missing, f"tools/{name}.py does not take {missing}, which the docs cite"


#: ``docs/<page>.md, "Section"`` as the code and the pages cite a page's section (the quote may
#: wrap onto the next line of a comment or docstring).
_CITATION = re.compile(r"docs/([\w/]+\.md)`?\)?,\s*(?:#:?\s*)?\"([^\"]+)\"")


def _sections(page: Path) -> list[str]:
    """A page's headings and its bold run-in labels (``**Sources.**``), as plain text."""
    text = page.read_text().replace("`", "")
    heads = [re.sub(r"\s*\{#.*\}\s*$", "", h) for h in re.findall(r"^#+ (.+)$", text, re.M)]
    labels = re.findall(r"^(?:- )?\*\*([^*]+)\*\*", text, re.M)
    return heads + [label.rstrip(".:") for label in labels]


def test_every_cited_docs_section_exists():
    """A comment or page that sends the reader to ``docs/<page>.md, "Section"`` names a page
    that exists and a section it has (a heading or a bold label starting with those words),
    so moving a section means updating the code that cites it."""
    files = [*(ROOT / "counterscene_env").rglob("*.py"), ROOT / "README.md", *DOCS.rglob("*.md")]
    for folder in ("tools", "tests", "agents", "examples"):
        files += sorted((ROOT / folder).glob("*.py"))
    checked = 0
    for path in files:
        for page, quoted in _CITATION.findall(path.read_text()):
            section = re.sub(r"\s*\n\s*(?:#:?\s*)?", " ", quoted).strip().rstrip(".,")
            target = DOCS / page
            where = f"{path.relative_to(ROOT)} cites docs/{page}, {section!r}"
            assert target.exists(), f"{where}: no such page"
            assert any(s.startswith(section.replace("`", "")) for s in _sections(target)), (
                f"{where}: the page has no such section"
            )
            checked += 1
    assert checked > 50, "the citation pattern no longer finds the code's citations"
