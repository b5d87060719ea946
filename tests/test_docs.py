"""The documentation stays true: every ```python block of README.md and docs/*.md runs, the
README stays short, relative links point to files (and headings) that exist, and docs/api.md
covers every public name.

Each block runs on its own, in a fresh namespace (``__name__ == "__main__"``, as a script), with
the working directory switched to a temporary directory: blocks write only relative paths and
keep their budgets tiny. Bash blocks are not executed.
"""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
# pages whose relative links are checked: the docs and the benchmark tables' notes
LINKED = [*PAGES, ROOT / "BENCHMARKS.md"]
MAX_README_LINES = 250

# a fenced block: its opening line (possibly indented, inside a list item) up to the closing fence
FENCE = re.compile(r"^([ \t]*)(```|~~~)[ \t]*([\w+-]*)[^\n]*\n(.*?)^\1\2[ \t]*$", re.M | re.S)
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
CODE_SPAN = re.compile(r"(`+).*?\1", re.S)


def _code_blocks(page: Path) -> list[tuple[str, int, str]]:
    """``(language, line of the opening fence, dedented body)`` of every fenced block."""
    text = page.read_text()
    return [
        (match.group(3), text.count("\n", 0, match.start()) + 1, textwrap.dedent(match.group(4)))
        for match in FENCE.finditer(text)
    ]


def _python_blocks() -> list:
    return [
        pytest.param(page, line, body, id=f"{page.relative_to(ROOT)}:{line}")
        for page in PAGES
        for language, line, body in _code_blocks(page)
        if language in ("python", "py")
    ]


@pytest.fixture
def one_thread():
    """One torch thread while a block runs: on 2 cores shared with other work, torch's default
    (a thread per core) makes small networks many times slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize(("page", "line", "body"), _python_blocks())
def test_python_block_runs(
    page: Path, line: int, body: str, tmp_path, monkeypatch, one_thread
) -> None:
    monkeypatch.chdir(tmp_path)
    # pad to the block's place in the page, so a traceback names the page's own line numbers
    source = "\n" * line + body
    namespace = {"__name__": "__main__"}
    exec(compile(source, str(page), "exec"), namespace)


def test_readme_is_short() -> None:
    lines = len(README.read_text().splitlines())
    assert lines <= MAX_README_LINES, f"README.md has {lines} lines (at most {MAX_README_LINES})"


def _prose(page: Path) -> str:
    """The page without its code blocks and code spans (no links there)."""
    return CODE_SPAN.sub("", FENCE.sub("", page.read_text()))


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = CODE_SPAN.sub(lambda m: m.group(0).strip("`"), heading.strip()).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6}[ \t]+(.+?)[ \t]*#*$", text, re.M)}


@pytest.mark.parametrize("page", LINKED, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path) -> None:
    broken = []
    for target in LINK.findall(_prose(page)):
        if re.match(r"[a-z][a-z0-9+.-]*:", target, re.I):  # https:, mailto: ...
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(f"{target}: no file {file}")
        elif anchor and file.suffix == ".md" and anchor not in _anchors(file):
            broken.append(f"{target}: no heading #{anchor} in {file.name}")
    assert not broken, f"broken links in {page.relative_to(ROOT)}: " + "; ".join(broken)


def test_readme_links_every_docs_page() -> None:
    prose = _prose(README)
    missing = [p.name for p in PAGES[1:] if f"(docs/{p.name}" not in prose]
    assert not missing, f"README.md does not link {missing}"


def test_api_page_covers_every_public_name() -> None:
    """Every name of ``rlpipe.__all__`` has a row (alone or with others) in the tables of
    docs/api.md's Names section, and the section names nothing else."""
    import rlpipe

    api = (ROOT / "docs" / "api.md").read_text()
    section = api.split("\n## Names\n", 1)[1].split("\n## ", 1)[0]
    first_cells = re.findall(r"^\| *(.+?) *\|", section, re.M)
    names = {m for cell in first_cells for m in re.findall(r"`(\w+)", cell)}
    missing = sorted(set(rlpipe.__all__) - names)
    assert not missing, f"docs/api.md's Names tables have no row for {missing}"
    unknown = sorted(names - set(rlpipe.__all__))
    assert not unknown, f"docs/api.md's Names tables list {unknown}, not in rlpipe.__all__"
