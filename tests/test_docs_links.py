"""Every relative link and image in README.md and docs/**/*.md points at a file that exists and, for `#anchor`
links, at a heading of that file (GitHub's slugs: lower case, punctuation dropped, each space a hyphen, repeats
numbered -1, -2, ...). External links (http, https, mailto) are not checked."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

FENCE = re.compile(r"^\s*(```|~~~)")
INLINE_CODE = re.compile(r"(`+)(?:(?!\1).)+?\1")
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
# The end of a link whose text began on an earlier line: "...](target)" with no "[" before it on this line.
WRAPPED_LINK_END = re.compile(r"^[^\[\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HEADING = re.compile(r"^ {0,3}(#{1,6})\s+(.*?)\s*#*\s*$")


def _prose_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) outside fenced code blocks."""
    lines, in_fence = [], False
    for number, line in enumerate(text.splitlines(), start=1):
        if FENCE.match(line):
            in_fence = not in_fence
            continue
        if not in_fence:
            lines.append((number, line))
    return lines


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a heading's text (before numbering repeats)."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text stays, its target goes
    text = re.sub(r"<[^>]+>", "", text).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)  # letters, digits, _ and - stay
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    result = set()
    for _, line in _prose_lines(path.read_text(encoding="utf-8")):
        match = HEADING.match(line)
        if not match:
            continue
        slug = github_slug(match.group(2))
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        result.add(slug if count == 0 else f"{slug}-{count}")
    return result


def broken_links(path: Path, root: Path = ROOT) -> list[str]:
    """Each relative link of a Markdown file whose target file or heading is missing, as 'file:line: target'."""
    problems = []
    for number, line in _prose_lines(path.read_text(encoding="utf-8")):
        prose = INLINE_CODE.sub("", line)
        for match in [*WRAPPED_LINK_END.finditer(prose), *LINK.finditer(prose)]:
            target = match.group(1)
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):  # http:, https:, mailto:
                continue
            file_part, _, anchor = target.partition("#")
            target_path = (path.parent / file_part).resolve() if file_part else path
            where = f"{path.relative_to(root)}:{number}: {target}"
            if not target_path.exists():
                problems.append(f"{where} (no such file)")
            elif anchor and target_path.suffix == ".md" and anchor not in anchors(target_path):
                problems.append(f"{where} (no such heading)")
    return problems


def markdown_files(root: Path = ROOT) -> list[Path]:
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def test_every_relative_link_in_readme_and_docs_resolves() -> None:
    files = markdown_files()
    assert len(files) >= 9, "README.md and the docs pages were not found"
    problems = [problem for path in files for problem in broken_links(path)]
    assert not problems, "broken links:\n" + "\n".join(problems)


def test_the_check_finds_a_missing_file_a_missing_heading_and_ignores_code(tmp_path: Path) -> None:
    (tmp_path / "docs" / "journal").mkdir(parents=True)
    (tmp_path / "docs" / "figures").mkdir()
    (tmp_path / "docs" / "figures" / "a.png").write_bytes(b"")
    (tmp_path / "docs" / "guide.md").write_text(
        "# Guide\n\n## Poses through images (`yoto bench --via-images`)\n\n## Measured\n\n## Measured\n"
    )
    page = tmp_path / "docs" / "journal" / "page.md"
    page.write_text(
        "# Journal\n\n"
        "[ok](../guide.md#poses-through-images-yoto-bench---via-images) [ok](../guide.md#measured-1)"
        " ![ok](../figures/a.png) [ok](#journal) [web](https://example.com/x.md)\n"
        "`[in code](nowhere.md)`\n```\n[in a fence](nowhere.md)\n```\n"
        "![moved one folder down, not fixed](figures/a.png)\n"
        "[a heading that is not there](../guide.md#measured-2)\n"
        "[a page that is not there](../tracking.md)\n"
        "[a link's text that wraps\nonto the next line](../guide.md#no-such-heading)\n"
    )
    assert broken_links(page, tmp_path) == [
        "docs/journal/page.md:8: figures/a.png (no such file)",
        "docs/journal/page.md:9: ../guide.md#measured-2 (no such heading)",
        "docs/journal/page.md:10: ../tracking.md (no such file)",
        "docs/journal/page.md:12: ../guide.md#no-such-heading (no such heading)",
    ]


@pytest.mark.parametrize(
    ("heading", "slug"),
    [
        ("Images as inputs: `yoto pose`, `yoto localize`", "images-as-inputs-yoto-pose-yoto-localize"),
        ("Pose result: `pair_NNNN.pose.json`", "pose-result-pair_nnnnposejson"),
        ("Stop 16, flat faces (2026-11-24): frames", "stop-16-flat-faces-2026-11-24-frames"),
        ("The real rig (`yoto rig`, [rig.md](rig.md))", "the-real-rig-yoto-rig-rigmd"),
    ],
)
def test_github_slug(heading: str, slug: str) -> None:
    assert github_slug(heading) == slug
