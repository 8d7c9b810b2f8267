"""One line when a fault starts and one when it ends, with the part's own reason; none per tick.

The rule alone (FaultWatch, measured_faults), then `carrt drive` on the car's rig through each
fault: a camera that stalls (stale, then lost), a receiver that goes quiet, a board whose
cable is pulled; the lines are counted in what the person reads.
"""

from __future__ import annotations

import time
from types import SimpleNamespace

import pytest
from e2e_rig import PAD_SETTINGS, CliRun, SyntheticPad, wait_for, write_video
from onnx_models import build_policy
from receiver_rig import GESTURE_S, NEUTRAL, RELEASE_S, VirtualCar, person_arms_and_gives_auto

from carrt.faults import FaultWatch, PartsWatch, measured_faults
from firmware_bridge import messages as m
from firmware_bridge.virtual import VirtualBoard

# timings in emulated or real time: their own pass in make test, not beside CPU-heavy tests
pytestmark = pytest.mark.realtime


def watch():
    lines: list[str] = []
    return FaultWatch(lambda now, line: lines.append(line), settle_s=0.5), lines


def test_a_fault_is_said_when_it_starts_and_when_it_has_been_over_for_the_settle_time():
    faults, lines = watch()
    for k in range(10):  # ten ticks of a camera getting older: one line, the first reason
        faults.update(k * 0.1, {"camera stale": f"newest frame {160 + 10 * k} ms old"})
    assert lines == ["camera stale: newest frame 160 ms old"]
    faults.update(1.0, {})
    faults.update(1.4, {})
    assert len(lines) == 1, "gone 0.4 s is not over yet"
    faults.update(1.5, {})
    assert lines[1] == "camera stale: over after 1.0 s"
    assert faults.active == ()


def test_a_fault_flickering_at_its_threshold_is_one_fault():
    faults, lines = watch()
    for k in range(20):
        faults.update(k * 0.1, {"camera stale": "x"} if k % 2 == 0 else {})
    assert lines == ["camera stale: x"]
    faults.update(3.0, {})
    assert lines == ["camera stale: x", "camera stale: over after 1.9 s"]


def test_two_faults_are_told_apart():
    faults, lines = watch()
    faults.update(0.0, {"camera stale": "a"})
    faults.update(0.1, {"camera stale": "a", "board silent": "b"})
    faults.update(0.2, {"board silent": "b"})
    faults.update(0.8, {"board silent": "b"})
    assert lines == ["camera stale: a", "board silent: b", "camera stale: over after 0.2 s"]


def measured(**given):
    base = {
        "frame_age_s": 0.03, "max_frame_age_s": 0.15, "camera_lost_reason": None,
        "connected": True, "telemetry": m.Telemetry(flags=int(m.TelemetryFlags.RC_SIGNAL)),
        "telemetry_age_s": 0.01, "max_telemetry_age_s": 0.1, "receiver_is_controls": True,
        "config_pending_s": None,
    }  # fmt: skip
    return measured_faults(**{**base, **given})


def test_each_fault_is_measured_with_its_reason():
    assert measured() == {}
    assert "180 ms old (limit 150 ms)" in measured(frame_age_s=0.18)["camera stale"]
    lost = measured(frame_age_s=1.2, camera_lost_reason="end of video file x: no new frame")
    assert lost == {"camera lost": "end of video file x: no new frame"}  # lost, not also stale
    assert "no telemetry for 250 ms" in measured(telemetry_age_s=0.25)["board silent"]
    assert "port is gone" in measured(connected=False)["board silent"]
    assert "receiver" in measured(telemetry=m.Telemetry(flags=0))["receiver lost"]
    assert measured(telemetry=m.Telemetry(flags=0), receiver_is_controls=False) == {}
    assert "arming is held" in measured(config_pending_s=0.8)["car config not on the board"]
    assert measured(config_pending_s=0.2) == {}


def parts_watch(receiver: str = "receiver"):
    link = SimpleNamespace(
        counters=SimpleNamespace(reboots_detected=0), board=None, connected=True,
        config_pending=False, telemetry_age_s=lambda: 0.01,
    )  # fmt: skip
    camera = SimpleNamespace(lost=False, lost_reason=None)
    config = SimpleNamespace(
        receiver=SimpleNamespace(controls=receiver), camera=SimpleNamespace(max_age_s=0.15),
        encoder=SimpleNamespace(max_age_s=0.1),
    )  # fmt: skip
    return PartsWatch(SimpleNamespace(link=link, camera=camera), config)


def tick_at(now: float, rc_signal: bool, heard: bool = True):
    flags = int(m.TelemetryFlags.RC_SIGNAL) if rc_signal else 0
    sample = SimpleNamespace(telemetry=m.Telemetry(flags=flags)) if heard else None
    return SimpleNamespace(now=now, frame=None, telemetry=sample)


def test_a_board_counting_its_first_pulses_is_not_a_lost_receiver_but_one_that_stays_off_is():
    watch_ = parts_watch()
    for k in range(4):  # the board not heard yet, then heard while it counts its 5 pulses
        watch_.faults_of(tick_at(k * 0.1, rc_signal=False, heard=k > 0))
    watch_.faults_of(tick_at(0.5, rc_signal=True))
    assert watch_.faults.active == () and watch_.notices == ()
    off = parts_watch()  # the transmitter off from the start: said once the board had the time
    for k in range(10):
        off.faults_of(tick_at(k * 0.1, rc_signal=False))
    assert [line for _t, line in off.notices] == [
        "receiver lost: the board has no valid pulse from the receiver (transmitter off, out of "
        "range or a wire loose; it needs 5 good pulses after a loss or a reboot)"
    ]
    pad = parts_watch(receiver="none")  # a pad holds the controls: the receiver is not a fault
    for k in range(10):
        pad.faults_of(tick_at(k * 0.1, rc_signal=False))
    assert pad.notices == ()


def count(output: str, text: str) -> int:
    return sum(text in line for line in output.splitlines())


@pytest.fixture
def board():
    with VirtualBoard() as vb:
        yield vb


def test_a_stalling_camera_is_one_stale_line_then_one_lost_line_with_its_reason(
    tmp_path, board, capsys
):
    short = write_video(tmp_path / "short.avi", seconds=1.5)
    model = build_policy(tmp_path / "policy.onnx")
    run = CliRun(
        [
            "drive", "--port", board.port, "--camera", str(short), "--out", str(tmp_path),
            "--model", str(model), "--duration", "6", "--set", "camera.loop_video=false",
            *(item for setting in PAD_SETTINGS for item in ("--set", setting)),
        ]
    )  # fmt: skip
    pad = SyntheticPad()
    pad.wait_ready()
    pad.connect_neutral()
    time.sleep(0.3)
    pad.press("arm")
    wait_for(lambda: board.state == m.State.ARMED)
    pad.press("auto")
    wait_for(lambda: board.state == m.State.ESTOP, timeout_s=5.0)  # camera lost: e-stop
    assert run.result() == 0
    out = capsys.readouterr()
    output = out.out + out.err
    assert count(output, "camera stale: newest frame") == 1, output
    assert count(output, "mode AUTO (neutral: camera frame older than 150 ms)") == 1, output
    assert count(output, "ms old") == 1, "the age is said once, in the fault's line"
    assert count(output, "camera lost: end of video file") == 1, output
    assert count(output, "e-stop: camera lost (end of video file") == 1, output


def test_a_receiver_gone_quiet_is_one_line_and_one_when_it_is_back(tmp_path, capsys):
    car = VirtualCar()
    try:
        video = write_video(tmp_path / "camera.avi")
        model = build_policy(tmp_path / "policy.onnx", steering=0.0, throttle=(0.5, 0.0))
        run = CliRun(
            [
                "drive", "--port", car.port, "--camera", str(video), "--out", str(tmp_path),
                "--model", str(model), "--duration", "10", "--set", "camera.loop_video=true",
                "--set", 'receiver.controls="receiver"',
                "--set", f"receiver.gesture_s={GESTURE_S}",
                "--set", f"receiver.release_s={RELEASE_S}",
            ]
        )  # fmt: skip
        person_arms_and_gives_auto(car)
        changes: list[tuple[m.State, m.Reason]] = []
        car.board.on_state_change = lambda _t, state, reason: changes.append((state, reason))
        car.board.receiver_off()
        wait_for(lambda: (m.State.FAILSAFE, m.Reason.RC_LOST) in changes, timeout_s=1.0)
        time.sleep(1.0)
        car.set_receiver(*NEUTRAL)
        assert run.result() == 0
    finally:
        car.close()
    out = capsys.readouterr()
    output = out.out + out.err
    assert count(output, "receiver lost: the board has no valid pulse") == 1, output
    assert count(output, "receiver lost: over after") == 1, output
    assert count(output, "mode ESTOP (neutral: e-stop: receiver lost)") == 1, output


def test_a_pulled_cable_is_one_board_silent_line_and_one_when_it_is_back(tmp_path, board, capsys):
    video = write_video(tmp_path / "camera.avi")
    run = CliRun(
        [
            "teleop", "--port", board.port, "--camera", str(video), "--out", str(tmp_path),
            "--duration", "7", "--set", "camera.loop_video=true",
            *(item for setting in PAD_SETTINGS for item in ("--set", setting)),
        ]
    )  # fmt: skip
    pad = SyntheticPad()
    pad.wait_ready()
    pad.connect_neutral()
    time.sleep(1.0)
    board.pull_cable()
    time.sleep(1.0)
    board.plug_cable()
    assert run.result() == 0
    out = capsys.readouterr()
    output = out.out + out.err
    assert count(output, "board silent:") == 2, output  # it started, and it is over
    assert count(output, "board silent: over after") == 1, output
