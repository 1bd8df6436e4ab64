"""Every relative link in the README and the docs points at a file that exists and, where it
names an anchor, at a heading of that file (GitHub's anchor rules): a moved section or a
renamed file breaks the front door silently otherwise."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "checkpoints" / "README.md", *sorted((ROOT / "docs").glob("*.md")),
         *sorted((ROOT / "docs" / "notebook").glob("*.md")),
         *sorted((ROOT / "results").glob("*.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def anchors(page: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation but '-' and '_' dropped, spaces to '-',
    a repeated heading numbered -1, -2, ..."""
    seen: dict[str, int] = {}
    out = set()
    for line in FENCE.sub("", page.read_text()).splitlines():
        if m := re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line):
            slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
            n = seen.get(slug, 0)
            seen[slug] = n + 1
            out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def links(page: Path) -> list[str]:
    return [t for t in LINK.findall(FENCE.sub("", page.read_text())) if not re.match(r"[a-z]+:", t)]


def test_slugs_follow_githubs_rules(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("# The pipeline on libero_spatial\n## Why: 3x, 40 it (seeds)\n## Why: 3x, 40 it (seeds)\n"
                    "```\n# not a heading\n```\n")
    assert anchors(page) == {"the-pipeline-on-libero_spatial", "why-3x-40-it-seeds", "why-3x-40-it-seeds-1"}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    broken = []
    for target in links(page):
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(f"{target}: no file {path}")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            broken.append(f"{target}: no heading #{anchor} in {file.relative_to(ROOT)}")
    assert not broken, "\n".join(broken)


def test_the_house_plan_names_every_module():
    """docs/development.md's layout names every module of the product and its wings by file name, so
    the list cannot drift from the tree (a new module without a line there fails here)."""
    plan = (ROOT / "docs" / "development.md").read_text()
    modules = [p for top in ("stages", "worldenv_core", "analysis", "benchmarks") for p in (ROOT / top).rglob("*.py")
               if p.name not in ("__init__.py", "__main__.py")]
    assert modules
    missing = sorted(str(p.relative_to(ROOT)) for p in modules if p.name not in plan)
    assert not missing, f"docs/development.md does not name {missing}"

