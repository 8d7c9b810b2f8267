"""docs/first-policy.md's recipe, end to end at a small size: the same command lines, read from
the guide's code block, with the sizes scaled down (a few placements, the `tiny` profile, a few
simulated seconds), each step's output checked. Torch runs only in the `carrt-train` and
`carrt-export` subprocesses, so this runs in the runtime test process."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "first-policy.md"
BIN = Path(sys.executable).parent

# the guide's size → the test's; each must occur in the recipe (a guide edit that drops one
# fails here instead of silently running the full size)
SCALE = {
    "--tracks 1000-1159": "--tracks 1000-1001",
    "--episodes 6": "--episodes 1",
    "--profile cpu": "--profile tiny",
    "--set imitation_steps=6000": "--set imitation_steps=30",
    "--tracks 100-104": "--tracks 100",
    "--seconds 60": "--seconds 5",
    "--duration 60": "--duration 5",
}


def recipe() -> list[str]:
    """The command lines of the code block under "## The recipe"."""
    section = GUIDE.read_text().split("## The recipe", 1)[1]
    block = re.search(r"```sh\n(.*?)```", section, flags=re.S)
    assert block, "docs/first-policy.md: no ```sh block under ## The recipe"
    return [line for line in block.group(1).splitlines() if line.strip()]


def scaled(lines: list[str]) -> list[str]:
    text = "\n".join(lines)
    for full, small in SCALE.items():
        assert full in text, f"the recipe no longer says {full!r}: update SCALE"
        text = text.replace(full, small)
    return text.splitlines()


def run(line: str, cwd: Path) -> str:
    argv = shlex.split(line)
    argv[0] = str(BIN / argv[0])
    done = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, f"{line}\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"
    return done.stdout + done.stderr


def test_the_recipe_has_the_five_steps():
    programs = [shlex.split(line)[:2] for line in recipe()]
    assert programs == [
        ["carrt-sim-data", "demos"],
        ["carrt-train", "--episodes"],
        ["carrt-export", "first/il/policy.pt"],
        ["carrt", "eval"],
        ["carrt", "drive"],
    ]


@pytest.mark.timeout(300)
def test_the_first_policy_recipe_end_to_end(tmp_path):
    record, train, export, evaluate, drive = scaled(recipe())
    first = tmp_path / "first"

    run(record, tmp_path)
    episodes = sorted(p.parent for p in (first / "demos").rglob("meta.json"))
    assert len(episodes) >= 2, "one episode per placement"
    for ep in episodes:
        meta = json.loads((ep / "meta.json").read_text())
        assert meta and (ep / "frames.u8").stat().st_size > 0

    run(train, tmp_path)
    for name in ("policy.pt", "policy.onnx", "report.md"):
        assert (first / "il" / name).exists(), name

    run(export, tmp_path)
    import onnxruntime as ort

    session = ort.InferenceSession(str(first / "policy.onnx"), providers=["CPUExecutionProvider"])
    assert len(session.get_inputs()) == 2 and session.get_outputs()
    assert session.get_modelmeta().custom_metadata_map, "carrt's metadata travels in the file"

    out = run(evaluate, tmp_path)
    assert "completion" in out
    result = json.loads((first / "eval.json").read_text())
    assert 0.0 <= result["aggregate"]["completion_ratio"]["mean"] <= 1.0
    assert len(result["runs"]) == 1

    out = run(drive, tmp_path)
    assert "completion ratio" in out
    assert (first / "drive.png").stat().st_size > 0
