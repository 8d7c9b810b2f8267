"""The person's line (research/person_line.py, issue 59 item 2): labels are where the person
drove from each frame, progress is metres along the line and nothing off it, the net trains on
the person's frames only, and planning for progress follows the line."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from research import ground_model as gm  # noqa: E402
from research import person_line as pl  # noqa: E402


def test_labels_are_the_persons_path_at_fixed_distances():
    """Straight at 1 m/s (0.1 m per step) for 40 steps, the person driving the first 30: from
    frame 0 the line's points lie 0.25 m apart straight ahead, up to where the person stopped
    driving (3 m would be past it: 2.5 m is the last); the policy's frames give none."""
    n = 40
    person = np.arange(n) < 30
    points, valid = pl.line_labels(gm.CarGeometry(), np.ones(n), np.zeros(n), person, np.array([]))
    assert valid[0].all()
    assert np.allclose(points[0, :, 0], 0.25 * np.arange(1, pl.POINTS + 1), atol=1e-6)
    assert np.allclose(points[0, :, 1], 0.0, atol=1e-6)
    assert valid[10].sum() == 8 and not valid[30:].any()  # 2.0 m left from frame 10
    # a collision event at step 5 ends the line there for the frames before it
    _, cut = pl.line_labels(gm.CarGeometry(), np.ones(n), np.zeros(n), person, np.array([5]))
    assert cut[0].sum() == 2  # 0.5 m of driving before the event: 0.25 and 0.5


def test_progress_is_metres_along_the_line_and_nothing_off_it():
    line = torch.tensor([[[0.25 * (k + 1), 0.0] for k in range(pl.POINTS)]])
    xy = torch.tensor([[[1.0, 0.1], [2.0, -0.2], [1.0, 0.8]]])
    s = pl.progress_along(line, xy)
    assert s[0, 0].item() == pytest.approx(1.0) and s[0, 1].item() == pytest.approx(2.0)
    assert s[0, 2].item() == 0.0  # 0.8 m beside the line: off it


def test_planning_for_progress_follows_the_line():
    """A line that bends right (y < 0) and a clear floor: the survival form picks a plan that
    steers right (+), the speed form cannot tell."""
    from research import ceiling

    model = gm.GroundWorldModel(gm.CarGeometry(), gm.MapGrid(), gm.SpeedResponse())
    model.hazard.forward = lambda image: torch.full((len(image), 40, 40), -8.0)
    ahead = torch.arange(1, pl.POINTS + 1) * 0.25
    bend = torch.stack([ahead * 0.8, -0.5 * ahead**2 / 2.5], dim=-1)[None]

    def line(image):
        return bend.expand(len(image), -1, -1)

    mu = np.tile([[0.0, 0.6]], (10, 1)).astype(np.float32)
    plans = ceiling.candidates(mu, 10, (-1.0, -1.0), (1.0, 1.0))
    image = np.zeros((96, 96, 3), np.uint8)
    best, scores = ceiling.choose_imagined((model, line), image, 1.5, plans, "survival",
                                           ceiling.Weights())  # fmt: skip
    assert plans[best, 0, 0] > 0.0
    names = [name for name, _, _ in ceiling.CANDIDATES]
    assert scores[names.index("steer+0.3")] > scores[0] > scores[names.index("steer-0.3")]


def test_it_trains_on_the_persons_frames_and_bad_input_is_one_line(tmp_path, capsys):
    demos = tmp_path / "demos"
    subprocess.run([sys.executable, "-m", "training.sim_data", "demos", "--out", str(demos),
                    "--tracks", "1000", "--layouts", "hard", "--episodes", "1"],
                   check=True, capture_output=True)  # fmt: skip
    run = tmp_path / "run"
    assert pl.main(["train", "--episodes", str(demos), "--out", str(run), "--steps", "3"]) == 0
    net = pl.load(run / "person_line.pt")
    assert net(torch.zeros(2, 96, 96, 3, dtype=torch.uint8)).shape == (2, pl.POINTS, 2)
    assert "frames the person drove on" in capsys.readouterr().out
    assert pl.main(["train", "--episodes", str(tmp_path / "none"), "--out", str(run)]) == 2
    assert capsys.readouterr().err.startswith("person_line: error: ")
