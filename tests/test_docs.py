"""The documentation a newcomer reads: a short README, links that lead
somewhere, no pointer to a design document outside the repository, and no
issue numbers in user pages."""
from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README_LIMIT_BYTES = 12_000
SKIP_DIRS = {".git", ".venv", "out", "dist", "__pycache__", "node_modules", ".pytest_cache"}

# the name of the team's map outside the repository, spelt so that this file
# does not mention it itself
OUTSIDE_MAP = "DESIGN" + ".md"
OUTSIDE_FOLDER = "/work/" + "shared"

INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
ISSUE_NUMBER = re.compile(r"\bissues?\s*#?\s*\d+", re.IGNORECASE)


def user_pages() -> list[Path]:
    pages = [ROOT / "README.md", ROOT / "blender_addon" / "README.md", ROOT / "scenes" / "README.md",
             ROOT / "lab" / "README.md"]
    pages += sorted((ROOT / "docs").glob("*.md")) + sorted((ROOT / "lenses").glob("*.md"))
    return [p for p in pages if p.is_file()]


def prose_lines(text: str) -> list[str]:
    """The lines outside fenced code blocks, inline code blanked out (a link
    or heading shown as code is not one)."""
    out, in_fence = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            in_fence = not in_fence
            out.append("")
            continue
        out.append("" if in_fence else re.sub(r"`[^`]*`", lambda m: " " * len(m.group()), line))
    return out


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: markup and punctuation dropped, lower
    case, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)     # a link's text
    text = text.lower().strip()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """Every heading's anchor in a Markdown file, duplicates numbered as GitHub does."""
    seen: dict[str, int] = {}
    found = set()
    in_fence = False
    for line in page.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line):
            in_fence = not in_fence
            continue
        m = None if in_fence else HEADING.match(line)
        if not m:
            continue
        base = slug(m.group(2))
        n = seen.get(base, 0)
        seen[base] = n + 1
        found.add(base if n == 0 else f"{base}-{n}")
    return found


def links(page: Path) -> list[tuple[int, str]]:
    """(line number, target) of every inline link and image outside code."""
    return [(i, m.group(1)) for i, line in enumerate(prose_lines(page.read_text(encoding="utf-8")), 1)
            for m in INLINE_LINK.finditer(line)]


def broken_links(page: Path) -> list[str]:
    problems = []
    for line_no, target in links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):     # http:, https:, mailto:
            continue
        path_part, _, anchor = target.partition("#")
        dest = page if not path_part else (page.parent / path_part).resolve()
        where = f"{page.relative_to(ROOT)}:{line_no}: {target}"
        if not dest.exists():
            problems.append(f"{where}: no such file")
        elif not dest.is_relative_to(ROOT):
            problems.append(f"{where}: points outside the repository")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            problems.append(f"{where}: no heading with the anchor #{anchor}")
    return problems


def repository_files(suffixes: tuple[str, ...]) -> list[Path]:
    found = []
    for p in ROOT.rglob("*"):
        rel = p.relative_to(ROOT).parts
        if any(part in SKIP_DIRS for part in rel) or not p.is_file():
            continue
        if p.suffix in suffixes:
            found.append(p)
    return found


def test_readme_is_short():
    size = (ROOT / "README.md").stat().st_size
    assert size <= README_LIMIT_BYTES, (f"README.md is {size} bytes, more than {README_LIMIT_BYTES}: "
                                        "move the detail to a page in docs/")


def test_the_pages_are_there():
    names = {p.relative_to(ROOT).as_posix() for p in user_pages()}
    for wanted in ("README.md", "docs/design.md", "docs/psf.md", "docs/image-formation.md", "docs/olf.md",
                   "docs/correction.md", "docs/pipeline.md", "docs/factory.md", "docs/addon.md",
                   "docs/scaling-out.md", "docs/performance.md"):
        assert wanted in names


@pytest.mark.parametrize("page", user_pages(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_links_and_images_resolve(page):
    assert broken_links(page) == []


def test_readme_shows_the_pipeline_first():
    lines = prose_lines((ROOT / "README.md").read_text(encoding="utf-8"))
    first_image = next(i for i, line in enumerate(lines) if "![" in line)
    first_section = next(i for i, line in enumerate(lines) if line.startswith("## "))
    assert first_image < first_section and "pipeline" in lines[first_image]


def test_no_pointer_to_a_design_document_outside():
    offenders = []
    for p in repository_files((".md", ".py", ".txt", ".toml", ".sh", ".cfg", ".yaml", ".sbatch")):
        text = p.read_text(encoding="utf-8", errors="replace")
        for i, line in enumerate(text.splitlines(), 1):
            if OUTSIDE_MAP in line or OUTSIDE_FOLDER in line:
                offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
    assert offenders == [], "say docs/design.md (the repository's own map) instead"


@pytest.mark.parametrize("page", user_pages(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_issue_numbers(page):
    found = [f"{i}: {m.group()}" for i, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1)
             for m in ISSUE_NUMBER.finditer(line)]
    assert found == []


def test_the_link_check_can_fail(tmp_path, monkeypatch):
    """A broken link, a missing anchor and a good link, in a page of a fake repository."""
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text("# A page\n\n## Set up: `build.py`, twice\n", encoding="utf-8")
    page = tmp_path / "README.md"
    page.write_text("[ok](docs/a.md#set-up-buildpy-twice) [gone](docs/b.md) ![pic](docs/x.png)\n"
                    "[bad anchor](docs/a.md#nowhere) `[in code](nowhere.md)`\n"
                    "```\n[in a fence](nowhere.md)\n```\n", encoding="utf-8")
    problems = broken_links(page)
    assert len(problems) == 3
    assert "docs/b.md: no such file" in problems[0] and "docs/x.png" in problems[1]
    assert "#nowhere" in problems[2]


def test_slugs_follow_github():
    assert slug("PSF accuracy against build time: how the defaults were chosen") == \
        "psf-accuracy-against-build-time-how-the-defaults-were-chosen"
    assert slug("The paper's tables at a 2-core machine's scale") == "the-papers-tables-at-a-2-core-machines-scale"
    assert slug("`dcdi dacn`") == "dcdi-dacn"
    assert slug("What ships in the add-on zip, and why") == "what-ships-in-the-add-on-zip-and-why"


def test_the_issue_check_can_fail():
    assert ISSUE_NUMBER.search("measured (issue 15, the simulation half)")
    assert ISSUE_NUMBER.search("see Issue #12")
    assert not ISSUE_NUMBER.search("an issue a user can act on, 15 times")


def test_the_source_rule_is_stated_from_the_code():
    """docs/psf.md quotes the rule as ``psf.rule`` words it, and no page or
    help restates an older order (the stores without the ray map)."""
    sys.path.insert(0, str(ROOT))
    from dcdi_core.psf.rule import RULE_ORDER, rule_text
    text = rule_text()
    page = " ".join((ROOT / "docs" / "psf.md").read_text(encoding="utf-8").split())
    assert "> " + text[0].upper() + text[1:] + "." in page
    assert list(RULE_ORDER) == ["basis", "raymap", "olf"]
    stale = re.compile(r"basis[^.]{0,60}else the OLF, else (the PSFs are )?trac", re.IGNORECASE)
    for p in user_pages():
        assert not stale.search(" ".join(p.read_text(encoding="utf-8").split())), p
