"""README's Layout section lists every package of the tree (and pipeline's top-level modules), so a reader's
map matches the code."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _layout_section() -> str:
    text = (REPO / "README.md").read_text()
    start = text.index("## Layout")
    return text[start:text.index("\n## ", start + 1)]


def test_readme_layout_names_every_package():
    section = _layout_section()
    packages = sorted({p.parent.relative_to(REPO) for top in ("pipeline", "service", "worker", "cli")
                       for p in (REPO / top).rglob("__init__.py")})
    missing = [str(p) for p in packages if f"{p.name}/" not in section]
    top_modules = [p.name for p in (REPO / "pipeline").glob("*.py") if p.name != "__init__.py"]
    missing += [m for m in top_modules if m not in section]
    assert not missing, f"README's Layout section does not mention: {missing}"
