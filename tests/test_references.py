"""No dead references in the product: every repository path, docs page and anchor that a
product file names (code, comments, messages, docs, README, Makefile) exists, and nothing cites
a design file the repository does not hold.

Why: a message that sends a user to "README, 'Flashing the firmware'" after that section moved
to docs/car.md, or a comment that cites "DESIGN §4" with no such file here, is a dead end for
the person reading it; they accumulate silently as files move.
"""

from __future__ import annotations

import re
from pathlib import Path

from test_docs_site import headings

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("carrt", "training", "export", "firmware_bridge", "docs")
SUFFIXES = {".py", ".md", ".c", ".h", ".ino", ".toml", ".yml", ".js", ".html", ".txt"}
TOP = ("carrt", "training", "export", "firmware_bridge", "docs", "research", "tests", "bench",
       ".ci")  # fmt: skip
PATH = re.compile(
    r"(?<![\w/.~-])((?:" + "|".join(re.escape(t) for t in TOP) + r")/[A-Za-z0-9_./-]*[A-Za-z0-9_/])"
    r"(#[a-z0-9-]+)?"
)
# What a command writes (not in the tree until it runs): named as outputs, not as references.
OUTPUTS = ("research/runs/", "bench/results/", "docs/_site/", "firmware_bridge/_build")
# Names with a slash that are not paths.
NOT_PATHS = {
    "carrt/Sim-v0": "the simulator's gymnasium id",
    "carrt/episode": "a column of a LeRobotDataset's meta/episodes (LeRobot nests with '/')",
    "carrt/first_step": "the same",
    "carrt/meta": "the same",
}


def exists(path: str) -> bool:
    """A file or folder, or a module named with its attribute (training/models.WorldModel)."""
    target = ROOT / path
    if target.exists() or target.with_suffix(".py").exists():
        return True
    module, _, _ = path.rpartition(".")
    return bool(module) and (ROOT / f"{module}.py").exists()


def product_files() -> list[Path]:
    files = [p for top in PRODUCT for p in (ROOT / top).rglob("*")
             if p.is_file() and p.suffix in SUFFIXES and "__pycache__" not in p.parts]  # fmt: skip
    files += [ROOT / name for name in ("README.md", "Makefile", "pyproject.toml", "mkdocs.yml")]
    return files


def references(text: str) -> list[tuple[str, str | None]]:
    found = []
    for match in PATH.finditer(text):
        path, anchor = match.group(1).rstrip("./"), match.group(2)
        if any(ch in text[match.end() : match.end() + 1] for ch in "*{<…") or "..." in path:
            continue  # a pattern (docs/*.md, runs/{name}/, …), not one file
        found.append((path, anchor[1:] if anchor else None))
    return found


def test_every_path_and_anchor_a_product_file_names_exists():
    dead = []
    for file in product_files():
        for path, anchor in references(file.read_text(errors="replace")):
            if path.startswith(OUTPUTS) or path in NOT_PATHS:
                continue
            target = ROOT / path
            if not exists(path):
                dead.append(f"{file.relative_to(ROOT)}: {path}")
            elif anchor and target.suffix == ".md" and anchor not in headings(target):
                dead.append(f"{file.relative_to(ROOT)}: {path}#{anchor}")
    assert not dead, "dead references:\n" + "\n".join(dead)


def test_nothing_cites_a_design_file_that_is_not_here():
    cites = [f"{f.relative_to(ROOT)}:{n}" for f in product_files()
             for n, line in enumerate(f.read_text(errors="replace").splitlines(), 1)
             if "DESIGN §" in line]  # fmt: skip
    assert not cites, "cite the paper or a docs page instead:\n" + "\n".join(cites)


def test_no_message_points_at_a_readme_section_the_readme_lacks():
    readme = {h.lower() for h in re.findall(r"^#+ (.+)$", (ROOT / "README.md").read_text(), re.M)}
    pointer = re.compile(
        r"README(?:\.md)?(?:'s)?,? (?:section )?(?:'([^']+)'|([A-Z][A-Za-z ]+?)\))"
    )
    dead = []
    for file in product_files():
        for match in pointer.finditer(file.read_text(errors="replace")):
            section = (match.group(1) or match.group(2)).strip()
            if section.lower() not in readme:
                dead.append(f"{file.relative_to(ROOT)}: README, {section!r}")
    assert not dead, "\n".join(dead)


def test_the_checker_finds_a_dead_path_an_anchor_and_skips_patterns():
    text = "see docs/car.md#no-such-heading and carrt/nothing_here.py; docs/*.md is a pattern"
    assert references(text) == [("docs/car.md", "no-such-heading"), ("carrt/nothing_here.py", None)]
