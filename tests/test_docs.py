"""The design notes in docs/ stay true to the code: names exist, cited anchors exist, no private
citations."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
EQUATIONS = DOCS / "equations.md"
CITING = ("src", "tests", "benchmarks")


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    s = heading.strip().lower()
    s = re.sub(r"[^\w\- ]", "", s)
    return s.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Heading anchors of a Markdown file (headings inside fenced code blocks are not headings)."""
    out: set[str] = set()
    seen: dict[str, int] = {}
    fenced = False
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
            continue
        m = None if fenced else re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            s = slug(m.group(1))
            n = seen.get(s, 0)
            seen[s] = n + 1
            out.add(s if n == 0 else f"{s}-{n}")
    return out


def resolve(dotted: str) -> object:
    """Import the longest module prefix of ``a.b.c.name`` and get the rest as attributes."""
    parts = dotted.split(".")
    for k in range(len(parts) - 1, 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ModuleNotFoundError:
            continue
        for attr in parts[k:]:
            obj = getattr(obj, attr)
        return obj
    raise ModuleNotFoundError(dotted)


def table_rows(text: str, first_header: str) -> tuple[list[str], list[list[str]]]:
    """Header cells and body rows of the Markdown table whose first header cell is
    ``first_header``."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and cells[0] == first_header:
            rows = []
            for body in lines[i + 2 :]:
                if not body.startswith("|"):
                    break
                rows.append([c.strip() for c in body.strip().strip("|").split("|")])
            return cells, rows
    raise AssertionError(f"no table with first column {first_header!r} in {EQUATIONS}")


def equation_names() -> list[str]:
    """Every code name in the equation tables, fully qualified."""
    text = EQUATIONS.read_text()
    names: list[str] = []
    for first in ("eq.", "map"):
        header, rows = table_rows(text, first)
        modules = [h.strip("`") if re.fullmatch(r"`evgrid(\.\w+)+`", h) else None for h in header]
        for row in rows:
            assert len(row) == len(header), (
                f"row {row[0]} has {len(row)} cells, the header {len(header)}"
            )
            for module, cell in zip(modules, row):
                for name in re.findall(r"`([\w.]+)`", cell):
                    if name.startswith("evgrid."):
                        names.append(name)
                    elif module is not None:
                        names.append(f"{module}.{name}")
    return names


def test_equation_table_numbers_every_equation_once():
    _, rows = table_rows(EQUATIONS.read_text(), "eq.")
    numbers = []
    for row in rows:
        lo_hi = [int(n) for n in re.findall(r"\((\d+)\)", row[0])]
        assert lo_hi, f"bad equation cell {row[0]!r}"
        numbers += list(range(lo_hi[0], lo_hi[-1] + 1)) if "-" in row[0] else lo_hi
    assert numbers == list(range(1, 38))  # the paper's 37 numbered equations, in order


def test_every_name_in_the_equation_tables_exists():
    names = equation_names()
    assert len(names) > 40 and "evgrid.mass.deep_discount_factor" in names
    missing = []
    for name in sorted(set(names)):
        try:
            resolve(name)
        except (ImportError, AttributeError):
            missing.append(name)
    assert not missing, f"docs/equations.md names what the code does not have: {missing}"


def test_tests_named_in_the_equation_table_exist():
    text = EQUATIONS.read_text()
    cited = re.findall(r"`(test_\w+)` in `(tests/[\w/]+\.py)`", text) + re.findall(
        r"property test `(test_\w+)`()", text
    )
    assert cited
    for name, path in cited:
        files = [ROOT / path] if path else sorted((ROOT / "tests").glob("test_*.py"))
        assert any(f"def {name}(" in f.read_text() for f in files), (
            f"no test {name} in {path or 'tests/'}"
        )


def _sources() -> list[Path]:
    files = [p for d in CITING for p in (ROOT / d).rglob("*.py")]
    return files + [ROOT / "README.md", *DOCS.glob("*.md")]


def test_cited_docs_anchors_exist():
    cited: list[tuple[Path, str, str]] = []
    for f in _sources():
        text = f.read_text()
        cited += [(f, p, a) for p, a in re.findall(r"(docs/[\w/.-]+?\.md)(?:#([\w-]+))?", text)]
        if f.parent == DOCS:  # relative links between the notes
            cited += [
                (f, f"docs/{p}", a)
                for p, a in re.findall(r"\]\(([\w-]+\.md)(?:#([\w-]+))?\)", text)
            ]
    assert len(cited) > 20
    bad = []
    for f, path, anchor in cited:
        target = ROOT / path
        if not target.is_file():
            bad.append(f"{f.relative_to(ROOT)}: {path} does not exist")
        elif anchor and anchor not in anchors(target):
            bad.append(f"{f.relative_to(ROOT)}: {path} has no heading #{anchor}")
    assert not bad, "\n".join(bad)


def test_slug_is_githubs():
    assert slug("Exact gamma bound") == "exact-gamma-bound"
    assert slug("The six maps of Table I") == "the-six-maps-of-table-i"
    assert slug("Ev-Net targets and loss") == "ev-net-targets-and-loss"
    assert slug("Occupied truth: surfaces, only!") == "occupied-truth-surfaces-only"


_DESIGN = re.compile(r"\bDESIGN\b")


def test_no_citations_of_the_private_design_notes():
    here = Path(__file__).resolve()
    citing = {
        str(f.relative_to(ROOT))
        for f in _sources()
        if f.resolve() != here and _DESIGN.search(f.read_text())
    }
    assert not citing, "cite docs/ or the paper's equation numbers instead of DESIGN"


@pytest.mark.parametrize("path", sorted(p.name for p in DOCS.glob("*.md")))
def test_docs_cite_no_private_files(path):
    text = (DOCS / path).read_text()
    assert "shared/" not in text and not _DESIGN.search(text)
