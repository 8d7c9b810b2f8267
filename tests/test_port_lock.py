"""A stand-in board refuses a port path another board holds (issue 60, item 6): in one line,
naming the holder, and without touching the first board's link; a crashed holder never
blocks the next board."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from avr_rig import start_emulator

from firmware_bridge.port_lock import PortPathHeld
from firmware_bridge.virtual import VirtualBoard


def test_a_second_virtual_board_on_a_held_path_refuses_and_leaves_the_link_alone(tmp_path):
    port = tmp_path / "ttyCAR"
    with VirtualBoard(port_path=port) as first:
        target = os.readlink(port)
        with pytest.raises(PortPathHeld) as exc:
            VirtualBoard(port_path=port)
        assert str(exc.value) == (
            f"{port}: another board (pid {os.getpid()}) is running on this port path; "
            "stop it or give this one another --port-path"
        )
        assert os.readlink(port) == target == first.pty_name  # the first board's link, still
    assert not os.path.lexists(port)  # the first board stopping removes its own link
    with VirtualBoard(port_path=port) as again:  # and the path is free again
        assert os.readlink(port) == again.pty_name


def test_an_emulated_board_and_a_virtual_one_share_the_rule(tmp_path):
    port = tmp_path / "ttyAVR"
    emulator = start_emulator(port_path=port)
    try:
        target = os.readlink(port)
        with pytest.raises(PortPathHeld):
            VirtualBoard(port_path=port)
        with pytest.raises(PortPathHeld):
            start_emulator(port_path=port)
        assert os.readlink(port) == target
    finally:
        emulator.close()


def _board_process(port) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, "-m", "firmware_bridge.virtual", "--port-path", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert proc.stdout is not None
    assert "virtual board ready" in proc.stdout.readline()
    return proc


def test_the_command_line_says_it_in_one_line_and_a_killed_holder_frees_the_path(tmp_path):
    port = tmp_path / "ttyCAR"
    holder = _board_process(port)
    try:
        second = subprocess.run(
            [sys.executable, "-m", "firmware_bridge.virtual", "--port-path", str(port)],
            capture_output=True, text=True, timeout=30,
        )  # fmt: skip
        assert second.returncode == 2 and second.stdout == ""
        assert second.stderr.strip() == (
            f"virtual board: error: {port}: another board (pid {holder.pid}) is running on this "
            "port path; stop it or give this one another --port-path"
        )
        assert os.path.lexists(port)
    finally:
        holder.send_signal(signal.SIGKILL)  # a crash: no cleanup runs
        holder.wait()
    deadline = time.monotonic() + 5
    while True:  # the kernel dropped the dead holder's lock
        try:
            with VirtualBoard(port_path=port):
                break
        except PortPathHeld:
            assert time.monotonic() < deadline
            time.sleep(0.05)
