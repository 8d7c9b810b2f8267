"""The commands the README and the guides in docs/ show, as data: which project program each
one runs, with which sub-commands and flags.

Why: the docs drift from the CLI unless something reads them the way a user does. This module
reads the shell code blocks (```sh / ```bash / ```console) and the CLI reference tables' first
cells, keeps the lines that run a project program (a console script from pyproject.toml, a make
target, `python -m <a package of this repository>`, `python <a file of this repository>`,
`torchrun … -m …`) and says what each one needs to exist. tests/test_docs_commands.py checks
those against `--help` (one call per program and sub-command).
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
SHELL_LANGS = {"sh", "bash", "shell", "console"}
FLAG = re.compile(r"(?<![\w./-])(--[A-Za-z][\w-]*|-[A-Za-z])(?![\w])")
# `{a,b}` not after a flag: a flag's choices (`--layout {empty,hard}`) are not sub-commands
SUBCOMMAND_CHOICES = re.compile(r"(?<![\w] )\{([\w,-]+)\}")


@dataclass(frozen=True)
class Command:
    """One command line of the docs: `argv[0]` is how to run the program (`carrt`, `make`,
    `python -m training.sim_data`, `python training/demo_policy.py`), then its words."""

    source: str  # file:line
    program: str
    words: tuple[str, ...]  # after the program: sub-commands, flags, values
    flags: tuple[str, ...]
    text: str


def doc_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def console_scripts() -> set[str]:
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return set(data["project"].get("scripts", {}))


def shell_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, command line) for each line in a shell code block, continuations joined."""
    out: list[tuple[int, str]] = []
    in_block, lang, pending, start = False, "", "", 0
    for n, raw in enumerate(path.read_text().splitlines(), start=1):
        stripped = raw.strip()
        if stripped.startswith("```"):
            if not in_block:
                in_block, lang = True, stripped[3:].strip().lower()
            else:
                in_block = False
            continue
        if not in_block or lang not in SHELL_LANGS:
            continue
        if stripped.startswith("$ "):
            stripped = stripped[2:]
        if not pending:
            start = n
        if stripped.endswith("\\"):
            pending += stripped[:-1] + " "
            continue
        out.append((start, pending + stripped))
        pending = ""
    return out


def table_commands(path: Path) -> list[tuple[int, str]]:
    """(line number, command) for each code span in the first cell of a table row, its
    `[optional]` parts included (the CLI reference's form)."""
    out: list[tuple[int, str]] = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.startswith("| `"):
            continue
        cell = re.split(r"(?<!\\)\| ", line[2:])[0]
        for code in re.findall(r"`([^`]+)`", cell):
            out.append((n, code.replace("\\|", "|")))
    return out


def split_commands(line: str) -> list[list[str]]:
    """The simple commands of one shell line (split at && || ; |), comments dropped; a line
    shlex cannot read (an unbalanced quote in prose) gives none."""
    try:
        lex = shlex.shlex(line, posix=True, punctuation_chars=";&|")
        lex.whitespace_split = True
        lex.commenters = "#"
        words = list(lex)
    except ValueError:
        return []
    commands, current = [], []
    for w in words:
        if w and set(w) <= set(";&|"):
            commands.append(current)
            current = []
        else:
            current.append(w)
    commands.append(current)
    return [c for c in commands if c]


def _is_repo_module(module: str) -> bool:
    top = module.split(".")[0]
    return (ROOT / top / "__init__.py").exists() or (ROOT / f"{top}.py").exists()


def classify(words: list[str], scripts: set[str]) -> tuple[str, list[str]] | None:
    """(program, its words) when `words` runs a project program, else None."""
    while (words and re.fullmatch(r"\w+=\S*", words[0])) or words[:1] == ["sudo"]:
        words = words[1:]
    if not words:
        return None
    head = Path(words[0]).name
    if head in scripts:
        return head, words[1:]
    if head == "make":
        return "make", words[1:]
    if head in {"python", "python3", "torchrun"} or re.fullmatch(r"python3\.\d+", head):
        rest = words[1:]
        while rest and rest[0].startswith("-") and rest[0] != "-m":
            # torchrun's own options (--nproc_per_node 4) and python's (-B, -u)
            rest = rest[2:] if head == "torchrun" and "=" not in rest[0] else rest[1:]
        if len(rest) >= 2 and rest[0] == "-m" and _is_repo_module(rest[1]):
            return f"python -m {rest[1]}", rest[2:]
        if rest and rest[0].endswith(".py") and (ROOT / rest[0]).exists():
            return f"python {rest[0]}", rest[1:]
        if rest and rest[0].endswith(".py") and not (ROOT / rest[0]).exists():
            return f"python {rest[0]}", rest[1:]  # a script the docs name that is not there
    return None


def commands(files: list[Path] | None = None) -> list[Command]:
    """The project commands in `files` (default: README.md and docs/*.md)."""
    scripts = console_scripts()
    found: list[Command] = []
    for path in doc_files() if files is None else files:
        rel = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name
        for n, line in shell_lines(path):
            for words in split_commands(line):
                hit = classify(words, scripts)
                if hit is not None:
                    program, rest = hit
                    found.append(
                        Command(f"{rel}:{n}", program, tuple(rest), tuple(flags_of(rest)), line)
                    )
        for n, cell in table_commands(path):
            # a reference cell: `[--opt ARG]`, `(a | b)` and `x|y` alternatives are syntax, so
            # its words are split on blanks and its flags found anywhere in it
            hit = classify(cell.split(), scripts)
            if hit is not None:
                program, rest = hit
                flags = FLAG.findall(" ".join(rest))
                found.append(Command(f"{rel}:{n}", program, tuple(rest), tuple(flags), cell))
    return found


def flags_of(words: tuple[str, ...]) -> list[str]:
    """The flags a command line uses (`--name` and `-x`; `--name=value` counts as `--name`)."""
    out = []
    for w in words:
        w = w.split("=")[0]
        if FLAG.fullmatch(w):
            out.append(w)
    return out


def help_flags(help_text: str) -> set[str]:
    """The flags argparse lists: those in the usage and at the start of an option's entry (not
    the ones a description or an example mentions)."""
    usage, _, rest = help_text.partition("\n\n")
    flags = set(FLAG.findall(usage))
    for line in rest.splitlines():
        if re.match(r"\s+-", line):
            flags |= set(FLAG.findall(re.split(r"(?<=\S)\s{2,}", line.strip(), maxsplit=1)[0]))
    return flags


def subcommand_choices(help_text: str) -> set[str]:
    """The sub-commands argparse lists: `{teleop,drive,…}` in the usage, or the entries under
    a COMMAND metavar in "positional arguments" (indented twice)."""
    usage, _, rest = help_text.partition("\n\n")
    found = {c for group in SUBCOMMAND_CHOICES.findall(usage) for c in group.split(",")}
    section = rest.split("positional arguments:", 1)[1] if "positional arguments:" in rest else ""
    for line in section.split("\n\n")[0].splitlines():
        m = re.match(r"^ {4}([a-z][\w-]*)(\s|$)", line)
        if m:
            found.add(m.group(1))
    return found


def make_targets() -> set[str]:
    text = (ROOT / "Makefile").read_text()
    return set(re.findall(r"^([A-Za-z][\w.-]*)\s*:(?!=)", text, flags=re.M))
