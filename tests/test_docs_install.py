"""The car's packages are stated once, in docs/install.md, and that statement is pyproject.toml's.

A list of what `pip install .` brings, kept by hand in three places, went stale in two of them
(the README and docs/architecture.md named four packages of seven); now the others point at
install.md and this test holds its row to the `dependencies` the wheel really declares.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: tomli, a runtime dependency there
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
CAR_ROW = "| the car (Jetson, any Linux SBC) | `pip install .` |"


def declared_runtime_packages() -> set[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    return {re.match(r"[A-Za-z0-9_.-]+", dep).group(0).lower() for dep in project["dependencies"]}


def install_page_packages() -> set[str]:
    rows = [
        ln
        for ln in (ROOT / "docs" / "install.md").read_text().splitlines()
        if ln.startswith(CAR_ROW)
    ]
    assert len(rows) == 1, "docs/install.md has one row for the car's install"
    brings = rows[0][len(CAR_ROW) :].split(":", 1)[0]  # "numpy, …, tomlkit (and tomli on 3.10)"
    words = re.findall(r"[A-Za-z][A-Za-z0-9_-]*", brings)
    return {w.lower() for w in words if w not in ("and", "on")}


def test_the_install_page_names_exactly_the_car_packages_pyproject_declares():
    assert install_page_packages() == declared_runtime_packages()


def test_no_other_page_lists_the_car_packages():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    for page in pages:
        if page.name == "install.md":
            continue
        for number, line in enumerate(page.read_text().splitlines(), 1):
            listed = sum(name in line for name in ("pyserial", "cobs", "pygame", "tomlkit"))
            assert listed < 3, f"{page.name}:{number} lists the car's packages again: {line}"
