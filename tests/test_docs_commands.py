"""Every command the README and docs/ show exists with its flags: the program, each sub-command
and each flag must appear in that program's `--help` (argparse's own listing), and every make
target must be in the Makefile. One `--help` per program and sub-command, in parallel."""

from __future__ import annotations

import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from pathlib import Path

from docs_commands import (
    ROOT,
    Command,
    commands,
    help_flags,
    make_targets,
    subcommand_choices,
)

BIN = Path(sys.executable).parent


def _argv(program: str) -> list[str]:
    if program.startswith("python -m "):
        return [sys.executable, "-m", program.removeprefix("python -m ")]
    if program.startswith("python "):
        return [sys.executable, str(ROOT / program.removeprefix("python "))]
    return [str(BIN / program)]


def _source(program: str) -> Path | None:
    """The file a `python -m X` or `python path.py` program runs, where it is in the tree."""
    if program.startswith("python -m "):
        base = ROOT / program.removeprefix("python -m ").replace(".", "/")
        for candidate in (base.with_suffix(".py"), base / "__main__.py"):
            if candidate.exists():
                return candidate
        return None
    if program.startswith("python "):
        path = ROOT / program.removeprefix("python ")
        return path if path.exists() else None
    return None


@cache
def help_text(program: str, chain: tuple[str, ...]) -> tuple[int, str]:
    """(exit code, --help output) of `program chain… --help`, run from the repository root. A
    module without argparse is not run (its `--help` may do its job instead): its help is the
    flags its source spells out."""
    source = _source(program)
    if source is not None and "argparse" not in (text := source.read_text()):
        flags = sorted(set(re.findall(r"[\"'](--?[A-Za-z][\w-]*)[\"']", text)))
        return 0, "usage: (read from the source)\n\n" + "".join(f"  {f}\n" for f in flags)
    try:
        done = subprocess.run(
            [*_argv(program), *chain, "--help"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
        )
    except FileNotFoundError:
        return 127, f"{program}: not installed"
    return done.returncode, done.stdout + done.stderr


def _walk(cmd: Command) -> tuple[list[tuple[str, ...]], str | None]:
    """The sub-command chains a command line names (several where `a|b` gives alternatives),
    or the reason its program's help cannot be read."""
    chains: list[tuple[str, ...]] = [()]
    for word in cmd.words:
        if word.startswith(("-", "[", "(")) or "…" in word:
            continue
        code, text = help_text(cmd.program, chains[0])
        if code != 0 or "usage:" not in text:
            return chains, f"`{cmd.program} {' '.join(chains[0])} --help` fails: " + (
                text.strip().splitlines() or ["(no output)"]
            )[-1]
        choices = subcommand_choices(text)
        parts = word.split("|")
        if choices and all(p in choices for p in parts):
            chains = [(*c, p) for c in chains for p in parts]
        elif choices:
            return chains, f"`{cmd.program} {' '.join(chains[0])}` has no sub-command {word}"
    return chains, None


def problems(found: list[Command]) -> list[str]:
    """One line per command of `found` that names a missing program, sub-command or flag."""
    out: list[str] = []
    targets = make_targets()
    for cmd in found:
        if cmd.program == "make":
            for word in cmd.words:
                if not word.startswith("-") and "=" not in word and word not in targets:
                    out.append(f"{cmd.source}: `make {word}`: no such target in the Makefile")
            continue
        chains, error = _walk(cmd)
        if error is None:
            for chain in chains:
                code, text = help_text(cmd.program, chain)
                if code != 0 or "usage:" not in text:
                    error = f"`{cmd.program} {' '.join(chain)} --help` fails: {text.strip()[-200:]}"
                    break
        if error is not None:
            out.append(f"{cmd.source}: {error}")
            continue
        known = set()
        for chain in chains:
            for depth in range(len(chain) + 1):
                known |= help_flags(help_text(cmd.program, chain[:depth])[1])
        missing = [f for f in dict.fromkeys(cmd.flags) if f not in known]
        if missing:
            where = f"{cmd.program} {' '.join(chains[0])}".strip()
            out.append(f"{cmd.source}: `{where}` has no {', '.join(missing)}: {cmd.text}")
    return out


def _prefetch(found: list[Command]) -> None:
    """Read every program's top-level help in parallel (the slow part: imports)."""
    programs = sorted({c.program for c in found if c.program != "make"})
    with ThreadPoolExecutor(max_workers=4) as pool:
        list(pool.map(lambda p: help_text(p, ()), programs))


def test_docs_show_commands_of_every_kind():
    found = commands()
    programs = {c.program for c in found}
    assert {"make", "carrt", "carrt-train", "carrt-export", "carrt-sim-data"} <= programs, programs
    assert any(c.source.startswith("README.md") for c in found)
    assert any(c.source.startswith("docs/") for c in found)


def test_every_documented_command_exists_with_its_flags():
    found = commands()
    _prefetch(found)
    bad = problems(found)
    assert not bad, "commands in the docs that the CLI does not have:\n" + "\n".join(bad)


def test_the_check_finds_a_missing_flag_subcommand_target_and_module(tmp_path):
    doc = tmp_path / "doc.md"
    doc.write_text(
        "```sh\n"
        "carrt drive --sim --no-such-flag 3   # a flag drive lacks\n"
        "carrt no-such-command --x\n"
        "make no-such-target\n"
        "python -m carrt.no_such_module --help\n"
        "carrt episodes ls episodes/ && carrt eval --model demo \\\n"
        "    --tracks 100\n"
        "```\n"
    )
    bad = problems(commands([doc]))
    text = "\n".join(bad)
    assert "--no-such-flag" in text
    assert "no-such-command" in text
    assert "make no-such-target" in text
    assert "carrt.no_such_module" in text
    assert len(bad) == 4, text  # the last line's two commands (joined across `\`) are fine


def set_problems(found: list[Command]) -> list[str]:
    """`--set KEY=VALUE` in the docs names a real setting: an TrainingConfig field for training
    (training/config.py), a `section.key` of the car's config for carrt (carrt/config.py)."""
    import dataclasses

    from carrt.config import CarConfig
    from training.config import TrainingConfig

    training_fields = {f.name for f in dataclasses.fields(TrainingConfig)}
    car = CarConfig()
    car_keys = {
        f"{s.name}.{f.name}"
        for s in dataclasses.fields(car)
        for f in dataclasses.fields(getattr(car, s.name))
    }
    out = []
    for cmd in found:
        values = [v for k, v in zip(cmd.words, cmd.words[1:], strict=False) if k == "--set"]
        for value in values:
            key = value.split("=")[0]
            if not key or key.upper() == key:  # a placeholder: FIELD=VALUE, K=V
                continue
            if cmd.program in {"carrt-train", "python -m training.iterate"}:
                ok = key in training_fields
            elif cmd.program == "carrt":
                ok = key in car_keys
            else:
                continue
            if not ok:
                out.append(f"{cmd.source}: `--set {value}`: no such setting for {cmd.program}")
    return out


def test_every_documented_set_names_a_real_setting():
    assert not (bad := set_problems(commands())), "\n".join(bad)
    sample = Command("doc.md:1", "carrt-train", ("--set", "no_such_field=1"), ("--set",), "")
    car = Command("doc.md:2", "carrt", ("drive", "--set", "noise.nope=1"), ("--set",), "")
    assert len(set_problems([sample, car])) == 2
