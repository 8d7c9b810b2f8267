"""Looking at episodes: summaries, rendering (video, overlay, contact sheet) and the CLI.

The summary counts what a person wants to know about a drive; the video holds every frame of
every episode, an .mp4 is H.264 a browser plays, and the `carrt episodes` commands list, show
and render. The episodes' format is in test_episodes.py.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from episode_factory import make_step, metadata, mixed_steps, run_cli, write_episode

from carrt.episodes import read_episode, video
from carrt.episodes.contact_sheet import render_contact_sheet
from carrt.episodes.summary import summarize
from carrt.episodes.video import render_video
from carrt.errors import UserError
from carrt.interfaces import Mode


# ----------------------------------------------------------------------------- inspection
def test_summary_counts(tmp_path):
    steps = []
    for i in range(20):
        mode = Mode.MANUAL if i < 16 else Mode.ESTOP
        steps.append(
            make_step(
                i,
                mode=mode,
                speed_mps=1.0 if i % 2 else 2.0,
                override=i in (3, 8),
                estop=i >= 16,
                noise=i < 5,
            )
        )
    steps[17].speed_mps = 9.0  # while in ESTOP: not part of the driving speed
    ep = read_episode(
        write_episode(tmp_path, steps, reason="estop", meta=metadata(model_sha256="f" * 64))
    )
    s = summarize(ep)
    assert s["frames"] == 20 and s["duration_s"] == pytest.approx(1.9)
    assert s["avg_speed_mps"] == pytest.approx(1.5) and s["top_speed_mps"] == pytest.approx(2.0)
    assert s["interventions"] == 2 and s["estops"] == 1 and s["noise_share"] == 0.25
    assert s["collisions"] == 2  # the e-stop edge at 16, and the end reason at 19
    assert s["collision_frames"] == 8  # 12..16 for the edge, 15..19 for the end
    assert s["end_reason"] == "estop"
    assert s["model_sha256"] == "f" * 64 and s["dropped"] == 0


@pytest.mark.parametrize("suffix", [".mp4", ".avi"])
def test_video_holds_every_episode_and_decodes(tmp_path, suffix):
    first = read_episode(write_episode(tmp_path / "a", mixed_steps(12)))
    second = read_episode(write_episode(tmp_path / "b", mixed_steps(5)))
    out = render_video([first, second], tmp_path / f"ep{suffix}", fps=10, scale=2)
    cap = cv2.VideoCapture(str(out))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    assert len(frames) == 17, "both episodes, every frame"
    assert frames[0].shape == (192, 192 + video.PANEL_W, 3)


def test_mp4_is_h264_a_browser_plays(tmp_path):
    """H.264 High, yuv420p, the moov atom before the media (playback starts while loading)."""
    import av

    ep = read_episode(write_episode(tmp_path, mixed_steps(12)))
    out = render_video([ep], tmp_path / "ep.mp4")
    with av.open(str(out)) as container:
        (stream,) = container.streams.video
        assert stream.codec_context.name == "h264"
        assert stream.codec_context.pix_fmt == "yuv420p"
        assert stream.codec_context.profile == "High"
        assert (stream.width, stream.height) == (384 + video.PANEL_W, 384)
        assert sum(1 for _ in container.decode(stream)) == 12
    head = out.read_bytes()[:4096]
    assert head.find(b"moov") != -1 and head.find(b"moov") < out.read_bytes().find(b"mdat")


def test_the_overlay_draws_the_actions_and_the_plan(tmp_path):
    ep = read_episode(write_episode(tmp_path, mixed_steps(12)))
    panel = video.compose(ep, 3)[:, 384:]
    other = video.compose(ep, 7)[:, 384:]
    assert panel.shape == (384, video.PANEL_W, 3)
    assert (panel != other).any(), "the panel follows the step"
    assert panel[250:, :].std() > 5, "the plan's lines are drawn"


def test_a_wrong_video_suffix_is_refused(tmp_path):
    ep = read_episode(write_episode(tmp_path, mixed_steps(3)))
    with pytest.raises(UserError, match=r"\.mp4 \(H\.264\)"):
        render_video([ep], tmp_path / "ep.mov")


def test_contact_sheet_decodes(tmp_path):
    ep = read_episode(write_episode(tmp_path, mixed_steps(25)))
    out = render_contact_sheet(ep, tmp_path / "sheet.png", every=2)
    sheet = cv2.imread(str(out))
    assert sheet.shape == (2 * (96 + 12), 10 * 96, 3)  # 13 tiles in rows of 10
    # tile 0 is frame 0 (RGB on disk, BGR in the PNG)
    np.testing.assert_array_equal(sheet[:96, :96, ::-1], ep.frames[0])


# ----------------------------------------------------------------------------- CLI


def test_cli_ls_show_video(tmp_path, capsys):
    path = write_episode(tmp_path, mixed_steps(10))
    assert run_cli(["episodes", "ls", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert path.name in out and "stopped" in out and "1 episodes" in out
    assert run_cli(["episodes", "show", str(path)]) == 0
    out = capsys.readouterr().out
    assert "interventions" in out and '"car_config"' not in out and len(out.splitlines()) < 30
    assert run_cli(["episodes", "show", str(path), "--meta"]) == 0
    assert '"car_config"' in capsys.readouterr().out
    assert run_cli(["episodes", "show", str(path), "--json", "--verify"]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 10
    assert run_cli(["episodes", "video", str(path), "--sheet", str(tmp_path / "s.png")]) == 0
    assert (tmp_path / "s.png").is_file()
    assert run_cli(["episodes", "video", str(path), "-o", str(tmp_path / "v.avi")]) == 0
    assert (tmp_path / "v.avi").stat().st_size > 0
    (tmp_path / "void").mkdir()
    with pytest.raises(UserError, match="no episodes in"):
        run_cli(["episodes", "ls", str(tmp_path / "void")])
