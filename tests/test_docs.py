"""The README's module table and docs/architecture.md are true to the tree."""

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "diffshadow"


def top_level_modules() -> set[str]:
    """Every module and sub-package directly under diffshadow/."""
    names = {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"}
    names |= {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    return {f"diffshadow.{n}" for n in names}


def table_modules(text: str) -> set[str]:
    rows = [line for line in text.splitlines() if line.startswith("| `diffshadow.")]
    return {m for row in rows for m in re.findall(r"`(diffshadow\.[\w.]+)`", row.split("|")[1])}


def test_readme_module_table_names_every_module_and_no_other():
    listed = table_modules((REPO / "README.md").read_text())
    actual = top_level_modules()
    assert listed - actual == set(), f"README names modules that do not exist: {sorted(listed - actual)}"
    assert actual - listed == set(), f"README's module table leaves out: {sorted(actual - listed)}"


def test_subpackage_parts_named_in_the_readme_exist():
    text = (REPO / "README.md").read_text()
    for package in ("render", "diffusion"):
        row = next(line for line in text.splitlines() if line.startswith(f"| `diffshadow.{package}` |"))
        named = set(re.findall(r"`(\w+)`", row.split("|")[2]))
        parts = {p.stem for p in (PACKAGE / package).glob("*.py") if p.stem != "__init__"}
        assert parts <= named | {"__init__"}, f"{package}: README leaves out {sorted(parts - named)}"
        assert {n for n in named if n.islower()} - parts == set(), sorted(named - parts)


def test_readme_is_short():
    assert len((REPO / "README.md").read_text().splitlines()) <= 200


def test_architecture_names_only_modules_that_exist():
    text = (REPO / "docs" / "architecture.md").read_text()
    for dotted in set(re.findall(r"`diffshadow\.([\w.]+)`", text)):
        path = PACKAGE.joinpath(*dotted.split("."))
        assert path.with_suffix(".py").is_file() or (path / "__init__.py").is_file(), dotted


def test_the_table_check_can_fail():
    assert table_modules("| `diffshadow.nothing` | x |\n") == {"diffshadow.nothing"}


PERFORMANCE = REPO / "docs" / "performance.md"
CITED = re.compile(r'performance\.md[,:]?\s*\(?\s*\\?"([^"\\]+)\\?"')
CITING = ("diffshadow", "tests", "scripts", "workflow", "config", "profiles", "docs")


def cited_sections(text: str) -> set[str]:
    """The names quoted after `docs/performance.md` in a file, a comment's continuation lines joined."""
    return set(CITED.findall(re.sub(r"\n\s*(?:#|\*)?\s*", " ", text)))


def performance_anchors(text: str) -> list[str]:
    """What a citation can name: each heading, and each bold lead of a paragraph or a bullet."""
    heads = [line.lstrip("#").strip() for line in text.splitlines() if line.startswith("#")]
    leads = re.findall(r"^\s*(?:- )?\*\*(.+?)\*\*", text, flags=re.MULTILINE)
    return [a.replace("`", "").lower() for a in heads + leads]


def test_sections_cited_in_the_tree_exist_in_performance_md():
    anchors = performance_anchors(PERFORMANCE.read_text())
    files = [REPO / "README.md", REPO / "Snakefile"]
    files += [p for d in CITING for p in (REPO / d).rglob("*") if p.suffix in {".py", ".yaml", ".md", ".smk", ".sh"}]
    missing = []
    for p in files:
        if p in (PERFORMANCE, Path(__file__)):
            continue
        for name in sorted(cited_sections(p.read_text())):
            if not any(a.startswith(name.replace("`", "").lower()) for a in anchors):
                missing.append(f"{p.relative_to(REPO)}: {name!r}")
    assert missing == [], f"cited sections docs/performance.md lacks: {missing}"


def test_the_citation_check_can_fail():
    cited = cited_sections('# x (docs/performance.md, "The\n# allocator")\n')
    assert cited == {"The allocator"}
    assert cited_sections('A = "see docs/performance.md, \\"The mix\\""\n') == {"The mix"}
    assert not any(a.startswith("no such section") for a in performance_anchors("## The allocator\n- **Lead** x\n"))
    assert performance_anchors("## `cache: auto`\n- **Lead** x\n") == ["cache: auto", "lead"]
