"""On the car nothing imports the simulator, gymnasium, matplotlib or torch: a real-car drive
(virtual board behind a pty, a video file as the camera, a real ONNX policy, recording armed),
then the car's report and episode listing, all in one process whose modules are inspected after."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from e2e_rig import write_video
from episode_factory import make_step, write_episode
from onnx_models import build_policy

from firmware_bridge.virtual import VirtualBoard

CAR_SESSION = """
import json, sys
from carrt.cli import main
codes = [main(argv) for argv in json.loads(sys.argv[1])]
loaded = sorted(sys.modules)
print(json.dumps({"codes": codes, "modules": loaded}))
"""

NOT_ON_THE_CAR = ("carrt.sim", "gymnasium", "matplotlib", "torch", "training", "export")


def test_a_real_car_session_imports_no_simulator_plots_or_torch(tmp_path):
    model = build_policy(tmp_path / "policy.onnx")
    video = write_video(tmp_path / "camera.avi")
    out = tmp_path / "episodes"
    # Nobody arms the car in this run, so the drive records nothing: its report and listing
    # read an episode the writer made, as one the car recorded earlier.
    write_episode(out, [make_step(i) for i in range(20)])
    with VirtualBoard() as board:
        commands = [
            ["drive", "--port", board.port, "--camera", str(video), "--model", str(model),
             "--record", "--out", str(tmp_path / "new"), "--duration", "1.5"],
            ["report", str(out)],
            ["episodes", "ls", str(out)],
        ]  # fmt: skip
        env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy"}
        result = subprocess.run(
            [sys.executable, "-c", CAR_SESSION, json.dumps(commands)],
            capture_output=True, text=True, timeout=120, env=env,
        )  # fmt: skip
    assert result.returncode == 0, result.stderr
    outcome = json.loads(result.stdout.strip().splitlines()[-1])
    assert outcome["codes"] == [0, 0, 0], result.stderr
    assert "carrt.loop" in outcome["modules"] and "onnxruntime" in outcome["modules"]
    leaked = [m for m in outcome["modules"] if m.split(".")[0] in NOT_ON_THE_CAR or
              m.startswith("carrt.sim")]  # fmt: skip
    assert leaked == []
