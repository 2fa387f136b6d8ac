"""Every reference to a finding or a result (``docs/<page>.md#<anchor>``) in the code and the docs names a
heading that exists, so a comment that cites a measurement always leads to it."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
REF = re.compile(r"docs/([\w-]+\.md)#([\w-]+)")
LINK = re.compile(r"\]\((?:\.\./)?(?:docs/)?([\w-]+\.md)#([\w-]+)\)")


def _anchors(page: Path) -> set[str]:
    """GitHub's anchors: the heading lower-cased, punctuation but hyphens and underscores dropped, spaces
    to hyphens."""
    out = set()
    for line in page.read_text().splitlines():
        m = re.match(r"#+\s+(.*)", line)
        if m:
            out.add(re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-"))
    return out


def test_every_cited_anchor_exists():
    anchors = {p.name: _anchors(p) for p in (ROOT / "docs").glob("*.md")}
    sources = [*ROOT.joinpath("src").rglob("*.py"), *ROOT.joinpath("tests").rglob("*.py"),
               *ROOT.joinpath("docs").glob("*.md"), ROOT / "README.md"]
    missing = []
    for path in sources:
        text = path.read_text()
        for page, anchor in {*REF.findall(text), *LINK.findall(text)}:
            if anchor not in anchors.get(page, set()):
                missing.append(f"{path.relative_to(ROOT)}: {page}#{anchor}")
    assert not missing, "references to missing headings:\n" + "\n".join(sorted(set(missing)))


def test_no_page_ships_a_placeholder():
    """A page a user reads never holds a stand-in for text or figures still to come."""
    marker = re.compile(r"(?<![\w-])[A-Z_]*(PLACEHOLDER|TODO|TBD|FIXME|XXX)\b")
    found = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}" for p in [*ROOT.joinpath("docs").glob("*.md"), ROOT / "README.md"]
             for i, line in enumerate(p.read_text().splitlines(), 1) if marker.search(line)]
    assert not found, "placeholders:\n" + "\n".join(found)
