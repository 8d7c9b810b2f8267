"""research/README.md's claims table: every claim reproduces by the command printed beside it.

Each claim that rests on a results file carries a command that computes its numbers from that
file in seconds (`research.robustness`, `research.paired_table`); they run here end to end, as a
user would type them but from another directory, and their output must hold every number the
table prints in bold. The runs that made the files train for an hour or more: their commands
must parse (every `--set` a real field), and every results file a claim names must be kept.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "research" / "README.md"
RESULTS = ROOT / "research" / "results"


def claims() -> list[dict]:
    """The claims table's rows: number, result cell, commands (backticked `python -m research.`
    or `python training/…` or `carrt …` or `make …`), results files."""
    rows = []
    for line in README.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 5 or not cells[0].isdigit():
            continue
        commands = [c for c in re.findall(r"`([^`]+)`", cells[3])
                    if c.startswith(("python ", "carrt ", "make "))]  # fmt: skip
        files = re.findall(r"`([^`]+)`", cells[4])
        rows.append({"n": int(cells[0]), "result": cells[2], "commands": commands,
                     "files": files})  # fmt: skip
    return rows


def bold_numbers(result: str) -> list[str]:
    """The bold "±" figures of a result cell, with the README's minus sign as the CLI prints it."""
    return [m.replace("−", "-") for m in re.findall(r"\*\*([−+-]?\d[^*]*± [\d.]+)\*\*", result)]


ROWS = claims()
QUICK = ("research.robustness", "research.paired_table")  # seconds, from kept results files


def quick_commands(row: dict) -> list[list[str]]:
    return [shlex.split(c) for c in row["commands"] if c.split()[2:3] and c.split()[2] in QUICK]


CHECKED = [r for r in ROWS if quick_commands(r)]


def run_as_file(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """`python -m research.x ARGS` as `python /repo/research/x.py ARGS` from `cwd`, the
    table's repository paths made absolute (the module itself is what runs)."""
    assert argv[:2] == ["python", "-m"]
    script = ROOT / Path(*argv[2].split(".")).with_suffix(".py")
    args = [str(ROOT / a) if a.startswith("research/") else a for a in argv[3:]]
    return subprocess.run([sys.executable, str(script), *args], cwd=cwd,
                          capture_output=True, text=True, timeout=120)  # fmt: skip


def test_the_table_has_its_claims():
    assert [r["n"] for r in ROWS] == list(range(1, len(ROWS) + 1))
    assert len(ROWS) >= 13  # the paper's claims and carrt's measured results
    assert len(CHECKED) >= 8


@pytest.mark.parametrize("row", ROWS, ids=lambda r: f"claim{r['n']}")
def test_each_claim_names_its_kept_results_and_a_command(row):
    assert row["files"], f"claim {row['n']} names no results file"
    for name in row["files"]:
        assert (RESULTS / name).is_file(), f"claim {row['n']}: research/results/{name} missing"
    assert row["commands"], f"claim {row['n']} has no command"


def test_results_earn_their_place():
    """research/results/ holds what the claims cite and nothing else, within the tree's budget
    (5 MB, 40 files, 8 figures): a superseded run leaves, and git history keeps it."""
    cited = {name for row in ROWS for name in row["files"]}
    held = {p.name for p in RESULTS.iterdir()}
    assert held == cited, f"not cited: {sorted(held - cited)}; missing: {sorted(cited - held)}"
    assert sum(p.stat().st_size for p in RESULTS.iterdir()) <= 5_000_000
    assert len(held) <= 40
    assert len([n for n in held if n.endswith(".png")]) <= 8


@pytest.mark.parametrize("row", CHECKED, ids=lambda r: f"claim{r['n']}")
def test_claims_reproduce_from_their_results_files(row, tmp_path):
    """Each quick command beside the claim, run from another directory: together their tables
    hold every bold number of the claim's result."""
    printed = ""
    for argv in quick_commands(row):
        out = run_as_file(argv, tmp_path)
        assert out.returncode == 0, out.stderr
        printed += out.stdout
    expected = bold_numbers(row["result"])
    assert expected, f"claim {row['n']} prints no bold number for its command to check"
    for number in expected:
        assert number in printed, f"claim {row['n']}: {number} not in\n{printed}"


def test_a_changed_number_fails_the_check(tmp_path):
    """The check can fail: a figure one digit off is not in the command's output."""
    row = CHECKED[0]
    number = bold_numbers(row["result"])[0]
    wrong = number[:-1] + str((int(number[-1]) + 1) % 10)
    out = run_as_file(quick_commands(row)[0], tmp_path)
    assert number in out.stdout and wrong not in out.stdout


STUDIES = {
    "research.takeover_check": ("research.takeover_config", "TakeoverConfig"),
    "research.refine_loop": ("research.refine_loop", "LoopConfig"),
    "research.world_model_swap": ("research.world_model_swap", "SwapConfig"),
}


@pytest.mark.parametrize("row", ROWS, ids=lambda r: f"claim{r['n']}")
def test_study_commands_name_real_settings(row):
    """Each study command of the table sets only fields its config (or StudyConfig, as
    `study.FIELD`) has, to values they accept: the long runs are not run here, but their
    commands cannot drift from the code. (`carrt` and `make` commands are the product's, checked
    with the README's.)"""
    import importlib

    from research.check_steps import read_sets

    for command in row["commands"]:
        argv = shlex.split(command)
        if argv[:2] != ["python", "-m"] or argv[2] not in STUDIES:
            continue
        module, name = STUDIES[argv[2]]
        config = getattr(importlib.import_module(module), name)
        _, cfg = read_sets(argv[3:], config(), argv[2], "doc", name)  # exit 2 on a wrong --set
        assert isinstance(cfg, config)


def test_a_wrong_setting_is_refused():
    from research.check_steps import read_sets
    from research.takeover_config import TakeoverConfig

    with pytest.raises(SystemExit) as exc:
        read_sets(["--set", "roundz=3"], TakeoverConfig(), "research.takeover_check", "d", "T")
    assert exc.value.code == 2


def test_the_shipped_policy_drives_as_recorded(tmp_path):
    """The shipped-policy claim's `carrt eval` command, on the one run of its ten that crashed
    (placement 103, seed 0; the whole command takes about a minute): the same laps, collisions
    and distance as its results file recorded."""
    (row,) = [
        r for r in ROWS if any(c.startswith("carrt eval --model demo") for c in r["commands"])
    ]
    (command,) = [c for c in row["commands"] if c.startswith("carrt eval --model demo")]
    argv = shlex.split(command)[2:]
    argv[argv.index("--tracks") + 1], argv[argv.index("--seeds") + 1] = "103", "0"
    argv[argv.index("--json") + 1] = str(tmp_path / "eval.json")
    out = subprocess.run([sys.executable, "-m", "carrt", "eval", *argv], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert out.returncode == 0, out.stderr
    (mine,) = json.loads((tmp_path / "eval.json").read_text())["runs"]
    recorded = json.loads((RESULTS / "demo_policy_eval.json").read_text())["runs"]
    (theirs,) = [r for r in recorded if (r["track"], r["seed"]) == (103, 0)]
    assert theirs["collisions"] >= 1  # the run that tells a policy apart
    for key in ("completion_ratio", "collisions", "laps", "distance", "average_speed"):
        assert mine[key] == pytest.approx(theirs[key], rel=1e-9), key
