"""A board that reboots under a driving car: `carrt drive` on the car's rig (a video file as the
camera, the board behind a pty, the RC receiver as the person's controls), the board rebooted
in AUTO three ways: the virtual board in place (a brown-out), a new virtual board on the same
port (a USB power cycle), and the firmware binary's reset on the emulated ATmega328P.

What must hold each time: the car stops and stays neutral and disarmed by itself; the person is
told once, by a line naming the reboot (not "joystick disconnected"); the host sends the car's
CONFIG again, so after the person re-arms the configured throttle limit holds (0.5: 1750 µs,
where the board's default would give the policy's full throttle, 2000 µs) and the receiver's
rules are the board's again (the switch e-stops on the board itself, a stick takes over); the
episode that was driving ends with the reboot as an event, and the next names the new boot.
"""

from __future__ import annotations

import time

import pytest
from e2e_rig import CliRun, wait_for, write_video
from onnx_models import build_policy
from receiver_rig import (
    GESTURE_S,
    NEUTRAL,
    RELEASE_S,
    AvrCar,
    VirtualCar,
    highest_throttle,
    person_arms_and_gives_auto,
)

from carrt.episodes.reader import list_episodes, read_episode

# timings in emulated or real time: their own pass in make test, not beside CPU-heavy tests
pytestmark = pytest.mark.realtime


def drive_through_a_reboot(tmp_path, car, reboot, capsys) -> tuple[list, str]:
    video = write_video(tmp_path / "camera.avi")
    model = build_policy(tmp_path / "policy.onnx", steering=0.0, throttle=(1.0, 0.0))
    out = tmp_path / "episodes"
    car.set_receiver(*NEUTRAL)
    run = CliRun(
        [
            "drive", "--port", car.port, "--camera", str(video), "--out", str(out),
            "--model", str(model), "--record", "--duration", "13",
            "--set", "camera.loop_video=true", "--set", "pwm.max_forward=0.5",
            "--set", 'receiver.controls="receiver"',
            "--set", f"receiver.gesture_s={GESTURE_S}", "--set", f"receiver.release_s={RELEASE_S}",
        ]
    )  # fmt: skip
    person_arms_and_gives_auto(car)
    before = highest_throttle(car, 1.0)
    assert 1700 <= before <= 1751, "the configured limit: 0.5 of the 500 µs span"

    reboot()
    # nothing drives by itself: neutral and disarmed for 2 s with the sticks let go
    wait_for(lambda: not car.armed() and car.pulses()[1] <= 1501, timeout_s=3.0)
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        assert not car.armed()
        assert car.pulses()[1] <= 1501  # no pulse yet while booting, or neutral
        time.sleep(0.01)

    person_arms_and_gives_auto(car)
    after = highest_throttle(car, 1.0)
    assert 1700 <= after <= 1751, f"the rebooted board got the car's config back ({after} µs)"

    car.set_receiver(1100, 1500, 1000)  # a stick in AUTO: the board hands over to the receiver
    wait_for(lambda: car.pulses()[0] < 1200 and abs(car.pulses()[1] - 1500) < 2, timeout_s=1.0)
    car.switch_estops_on_the_board()
    assert run.result(timeout_s=30.0) == 0
    captured = capsys.readouterr()
    episodes = [read_episode(p) for p in list_episodes(out)]
    return episodes, captured.out + captured.err


def check_told_once_and_recorded(episodes, output: str, cause: str) -> None:
    """One line names the reboot; the episode that was driving ends with it or, when the board
    went silent first (power off: its watchdog stopped the car and the host disarmed), as that
    failsafe; either way the next episode names the new boot."""
    lines = [line for line in output.splitlines() if "board rebooted" in line]
    assert len(lines) == 1, output
    assert f"board rebooted ({cause}" in lines[0]
    assert "joystick disconnected" not in output
    first, second = episodes[0], episodes[1]
    assert second.meta["board"]["boot_id"] != first.meta["board"]["boot_id"]
    assert second.meta["board"]["reset_cause"] == cause and "events" not in second.meta
    assert first.meta["end_reason"] in ("reboot", "failsafe"), first.meta["end_reason"]
    if first.meta["end_reason"] == "reboot":
        (event,) = first.meta["events"]
        assert event["kind"] == "board_reboot" and event["reset_cause"] == cause
        assert 0 < event["step"] <= first.meta["counts"]["steps"]
        assert second.meta["board"]["boot_id"] == event["boot_id"]
    else:
        assert "events" not in first.meta and "board silent" in output


@pytest.fixture
def car():
    vehicle = VirtualCar()
    yield vehicle
    vehicle.close()


def test_a_virtual_board_browning_out_while_driving(tmp_path, car, capsys):
    episodes, output = drive_through_a_reboot(tmp_path, car, car.brown_out, capsys)
    check_told_once_and_recorded(episodes, output, "brown-out")
    assert episodes[0].meta["end_reason"] == "reboot", "in place, the port stays: seen driving"


def test_a_virtual_board_restarted_on_the_same_port_while_driving(tmp_path, car, capsys):
    episodes, output = drive_through_a_reboot(tmp_path, car, car.restart_on_same_port, capsys)
    check_told_once_and_recorded(episodes, output, "power-on")


def test_the_emulated_avr_reset_while_driving(tmp_path, capsys):
    car = AvrCar()
    try:
        episodes, output = drive_through_a_reboot(tmp_path, car, car.reset, capsys)
    finally:
        car.close()
    check_told_once_and_recorded(episodes, output, "reset pin")
