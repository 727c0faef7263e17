"""The README and the pages under docs/: the README stays short and opens with the two commands, and every relative
link of the README and of the pages (files, and #anchors of Markdown headings) resolves. Reads files only: fast."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = sorted((ROOT / "docs").rglob("*.md"))
MAX_README_LINES = 150

FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
CODE_SPAN = re.compile(r"`[^`\n]*`")
LINK = re.compile(r"!?\[[^\]\n]*\]\(([^)\s]+)\)")
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.M)


def links(path: Path) -> list[str]:
    """The link targets of a Markdown file, outside code blocks and code spans."""
    text = CODE_SPAN.sub("", FENCE.sub("", path.read_text(encoding="utf-8")))
    return LINK.findall(text)


def anchor(heading: str) -> str:
    """GitHub's (and MyST's ``myst_heading_anchors``) anchor of a heading: lower case, punctuation dropped, spaces to -."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()  # a link's text
    text = re.sub(r"[^\w\- ]", "", text.replace("`", ""))
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = FENCE.sub("", path.read_text(encoding="utf-8"))
    return {anchor(heading) for heading in HEADING.findall(text)}


def test_readme_is_short_and_opens_with_the_two_commands():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines, at most {MAX_README_LINES}"
    # the project's rule: the set-up commands come first, right under the title
    assert lines[0].startswith("# ")
    start = lines.index("```bash")
    assert start <= 3, "the README opens with the commands block"
    block = lines[start : lines.index("```", start)]
    assert any(line.startswith("make demo") for line in block) and any(line.startswith("make test") for line in block)


def test_anchor_matches_github_slugs():
    assert anchor("HER: PandaReach-v3 (issue 18, 2026-12-01)") == "her-pandareach-v3-issue-18-2026-12-01"
    assert anchor("Images: `CnnPolicy`") == "images-cnnpolicy"
    assert anchor("Choosing SOUP's defaults (issue 11, 2026-11-30)") == "choosing-soups-defaults-issue-11-2026-11-30"


@pytest.mark.parametrize("path", [README, *PAGES], ids=lambda path: str(path.relative_to(ROOT)))
def test_relative_links_resolve(path: Path):
    broken = []
    for target in links(path):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:, ...
            continue
        file_part, _, fragment = target.partition("#")
        linked = (path.parent / file_part).resolve() if file_part else path
        if not linked.exists():
            broken.append(f"{target} (no {linked.relative_to(ROOT) if linked.is_relative_to(ROOT) else linked})")
        elif fragment and linked.suffix == ".md" and fragment not in anchors(linked):
            broken.append(f"{target} (no heading #{fragment} in {linked.relative_to(ROOT)})")
    assert not broken, f"{path.relative_to(ROOT)}: broken links: {broken}"


def test_every_page_is_linked_from_the_readme():
    """The README is the entry point on GitHub (and the documentation's front page): it links every page of docs/."""
    linked = {(README.parent / target.partition("#")[0]).resolve() for target in links(README)}
    pages = {page.resolve() for page in (ROOT / "docs").glob("*.md") if page.name != "index.md"}
    pages |= {(ROOT / "docs" / "api.rst").resolve()}
    missing = sorted(str(page.relative_to(ROOT)) for page in pages - linked)
    assert not missing, f"README.md does not link {missing}"
