"""The real command lines: `python -m firmware_bridge.virtual` and `carrt check` as processes."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from firmware_bridge import messages as m
from firmware_bridge.virtual import VirtualBoard

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def carrt(*args, timeout=30):
    return subprocess.run(
        [sys.executable, "-m", "carrt", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=ENV,
    )


@pytest.fixture
def virtual_board_process(tmp_path):
    """The virtual board as a user starts it: its own process, port path printed on stdout."""
    port = tmp_path / "ttyCARRT0"
    proc = subprocess.Popen(
        [sys.executable, "-m", "firmware_bridge.virtual", "--port-path", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )
    ready, _, _ = select.select([proc.stdout], [], [], 30)
    line = proc.stdout.readline() if ready else ""
    if "virtual board ready on" not in line:
        proc.kill()
        pytest.fail(f"virtual board did not start: {line}{proc.stderr.read()}")
    assert str(port) in line
    yield str(port), proc
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=5)


def test_check_reports_a_healthy_virtual_board(virtual_board_process):
    port, proc = virtual_board_process
    result = carrt("check", "--port", port, "--spin-wheels")
    assert result.returncode == 0, result.stdout + result.stderr
    out = result.stdout
    for section in ("handshake", "round trip", "telemetry", "state", "encoder", "errors"):
        assert section in out
    assert f"protocol {m.PROTOCOL_HASH:08x}" in out
    assert "FAIL" not in out
    assert out.strip().endswith("healthy")

    proc.send_signal(signal.SIGINT)
    stdout, _ = proc.communicate(timeout=5)
    assert proc.returncode == 0
    assert "ARMED" in stdout, "the virtual board logs its state changes"


def test_check_without_a_board_is_one_line_and_exit_2(tmp_path):
    result = carrt("check", "--port", str(tmp_path / "ttyUSB9"))
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1
    assert "does not exist" in result.stderr and "ttyUSB9" in result.stderr
    assert "Traceback" not in result.stderr


def test_check_flags_an_encoder_that_does_not_tick():
    from firmware_bridge.drivetrain import WheelPlant

    with VirtualBoard(WheelPlant(blocked=True)) as board:
        result = carrt("check", "--port", board.port, "--spin-wheels", "--pings", "5")
    assert result.returncode == 1
    assert "unhealthy" in result.stdout and "encoder" in result.stdout


def test_killed_host_process_leaves_the_car_stopped(tmp_path):
    with VirtualBoard() as board:
        script = textwrap.dedent(
            f"""
            import time
            from firmware_bridge.link import BoardLink
            link = BoardLink({board.port!r}).open()
            time.sleep(0.2)  # the board arms once the wheels have been still for 100 ms
            link.arm()
            print("driving", flush=True)
            while True:
                link.set_command(0.1, 0.4)
                time.sleep(0.02)
            """
        )
        proc = subprocess.Popen(
            [sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, env=ENV
        )
        try:
            assert proc.stdout.readline().strip() == "driving"
            deadline = time.monotonic() + 3
            while board.throttle_us <= 1500 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert board.throttle_us > 1500
            proc.kill()
            killed = time.monotonic()
            while board.state != m.State.FAILSAFE and time.monotonic() - killed < 2:
                time.sleep(0.001)
            assert board.state == m.State.FAILSAFE
            assert time.monotonic() - killed <= 0.25
            assert board.reason == m.Reason.LINK_TIMEOUT
            assert board.throttle_us == 1500
        finally:
            proc.kill()
            proc.wait()
