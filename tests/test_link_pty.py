"""Host link against the virtual board over a real pty: real pyserial, real C core, no mocks.

Timing bounds here are generous on purpose (a loaded 2-core CI machine); exact timing of the
failsafes is proven with a fake clock in test_firmware_core.py, and latencies are measured in
bench/.
"""

from __future__ import annotations

import functools
import os
import time

import pytest
from e2e_rig import wait_for as rig_wait_for

from firmware_bridge import messages as m
from firmware_bridge.link import ArmRefused, BoardLink, ProtocolMismatch
from firmware_bridge.virtual import VirtualBoard

# The link tests keep their own tighter defaults: 2 s, polled every millisecond.
wait_for = functools.partial(rig_wait_for, timeout_s=2.0, interval_s=0.001)


@pytest.fixture
def board():
    with VirtualBoard() as vb:
        yield vb


@pytest.fixture
def link(board):
    with BoardLink(board.port) as ln:
        # The board only arms once it has seen the wheels still for 100 ms since boot.
        wait_for(lambda: ln.telemetry is not None and ln.telemetry.telemetry.mcu_time_ms > 150)
        yield ln


def drive(link, steering, throttle, seconds):
    """Behave like a control loop: a new decision every 20 ms for `seconds`."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        link.set_command(steering, throttle)
        time.sleep(0.02)


def test_handshake_reports_the_board(link):
    assert link.board is not None
    assert link.board.protocol_hash == m.PROTOCOL_HASH
    assert link.board.firmware_version == m.FIRMWARE_VERSION
    wait_for(lambda: link.telemetry is not None)
    assert link.board_state == m.State.DISARMED


def test_commands_reach_the_pulses_only_when_armed(board, link):
    drive(link, 0.5, 0.0, 0.1)
    assert board.steer_us == 1500, "a disarmed board keeps its outputs neutral"
    link.arm()
    drive(link, 0.5, 0.3, 0.4)
    assert board.steer_us == 1750
    assert board.throttle_us == 1650  # 0.3 of the 500 us span above neutral, after the slew
    tel = link.telemetry.telemetry
    assert (tel.steer_us, tel.throttle_us) == (1750, 1650)
    assert tel.state == m.State.ARMED


def test_encoder_ticks_reach_telemetry(board, link):
    link.arm()
    first = link.telemetry.telemetry.encoder_ticks
    drive(link, 0.0, 0.5, 0.8)
    ticks = link.telemetry.telemetry.encoder_ticks - first
    assert ticks > 50, "the wheel turned under throttle"
    expected = board.plant.ticks
    assert abs(link.telemetry.telemetry.encoder_ticks - expected) <= 20  # one telemetry period


def test_garbage_in_both_directions_is_dropped_and_driving_continues(board, link):
    link.arm()
    rng = __import__("random").Random(7)
    for _ in range(20):
        board.inject_to_board(bytes(rng.randrange(256) for _ in range(40)))
        board.inject_to_host(bytes(rng.randrange(1, 256) for _ in range(40)) + b"\x00")
        link.set_command(0.2, 0.2)
        time.sleep(0.02)
    drive(link, 0.2, 0.2, 0.2)
    assert board.state == m.State.ARMED, "noise must not trip or disarm a healthy link"
    board_drops = board.counters["bad_crc"] + board.counters["bad_length"]
    assert board_drops > 0
    assert link.counters.bad_crc + link.counters.bad_length > 0
    assert board.steer_us == 1600


def test_pulled_cable_fails_safe_within_200ms_and_reconnect_does_not_drive(board, link):
    link.arm()
    drive(link, 0.3, 0.4, 0.3)
    assert board.throttle_us > 1500
    board.pull_cable()
    pulled = time.monotonic()
    wait_for(lambda: board.state == m.State.FAILSAFE, timeout_s=1.0)
    # The last command left the host at most one send period before the pull.
    assert time.monotonic() - pulled <= 0.2 + 0.05
    assert board.reason == m.Reason.LINK_TIMEOUT
    assert (board.steer_us, board.throttle_us) == (1500, 1500)
    wait_for(lambda: not link.connected, timeout_s=1.0)

    board.plug_cable()
    wait_for(lambda: link.connected, timeout_s=3.0)
    assert link.counters.reconnects == 1
    drive(link, 0.3, 0.4, 0.3)  # the control loop carries on as if nothing happened
    assert board.state == m.State.FAILSAFE, "a reconnect alone never resumes driving"
    assert board.throttle_us == 1500

    link.set_command(0.0, 0.0)
    link.clear()
    assert board.state == m.State.DISARMED
    wait_for(lambda: board.plant.speed_mps == 0.0)  # the car coasts to a stop first
    time.sleep(0.15)
    link.arm()
    drive(link, 0.0, 0.2, 0.3)
    assert board.throttle_us == 1600


def test_reboot_on_reconnect_is_detected_and_leaves_the_car_disarmed():
    with VirtualBoard(reset_on_open=True) as board, BoardLink(board.port) as link:
        first_boot = link.board.boot_id
        time.sleep(0.15)
        link.arm()
        board.pull_cable()
        board.plug_cable()
        wait_for(lambda: link.counters.reconnects == 1, timeout_s=3.0)
        assert link.counters.reboots_detected == 1
        assert link.board.boot_id != first_boot
        drive(link, 0.0, 0.3, 0.3)
        assert board.state == m.State.DISARMED
        assert board.throttle_us == 1500


def test_hung_control_loop_trips_decision_freshness(board, link):
    link.arm()
    drive(link, 0.0, 0.2, 0.2)
    stopped = time.monotonic()  # the loop hangs; the sender thread keeps the link alive
    wait_for(lambda: board.state == m.State.FAILSAFE, timeout_s=1.5)
    assert board.reason == m.Reason.DECISION_STALE
    assert time.monotonic() - stopped >= 0.28
    assert link.connected


def test_clear_right_after_a_failsafe_is_not_fooled_by_older_telemetry(board, link):
    """The last telemetry may predate the failsafe (still ARMED); clear must wait for its ack."""
    for _ in range(5):
        link.wait_until_still()
        link.arm()
        drive(link, 0.0, 0.1, 0.1)
        wait_for(lambda: board.state == m.State.FAILSAFE, timeout_s=1.5)
        link.set_command(0.0, 0.0)
        link.clear()
        assert board.state == m.State.DISARMED


def test_estop_goes_out_at_once_not_at_the_next_send_tick(board):
    # With the periodic sender slowed to 1 Hz, only the immediate path can explain a fast e-stop.
    with BoardLink(board.port, send_period_s=1.0) as link:
        time.sleep(0.05)
        link.estop()
        took = wait_for(lambda: board.state == m.State.ESTOP, timeout_s=0.5)
        assert took < 0.2
        with pytest.raises(ArmRefused, match="e-stop"):
            link.arm()


def test_estop_is_latched_until_clear_then_a_separate_arm(board, link):
    link.arm()
    drive(link, 0.0, 0.3, 0.2)
    link.estop()
    wait_for(lambda: board.state == m.State.ESTOP)
    assert board.throttle_us == 1500
    drive(link, 0.0, 0.3, 0.3)
    assert board.state == m.State.ESTOP
    link.set_command(0.0, 0.0)
    link.clear()
    assert board.state == m.State.DISARMED
    drive(link, 0.0, 0.0, 0.1)
    assert board.state == m.State.DISARMED, "clearing never re-arms by itself"


def test_arming_with_throttle_applied_is_refused_with_the_reason(link):
    link.set_command(0.0, 0.5)
    with pytest.raises(ArmRefused, match="throttle not neutral"):
        link.arm()


def test_config_round_trip_and_refused_while_armed(board, link):
    config = m.Config(steer_left_us=1100, steer_center_us=1480, steer_right_us=1900, persist=1)
    ack = link.send_config(config)
    assert ack.result == m.ConfigResult.ACCEPTED and ack.persisted == 1
    read = link.read_config()
    assert (read.steer_left_us, read.steer_center_us, read.steer_right_us) == (1100, 1480, 1900)
    drive(link, 0.0, 0.0, 0.05)
    assert board.steer_us == 1480
    link.arm()
    assert link.send_config(m.Config()).result == m.ConfigResult.REJECTED_ARMED


def test_ping_round_trip(link):
    rtts = [link.ping() for _ in range(10)]
    assert all(0 < rtt < 0.25 for rtt in rtts)


def test_protocol_mismatch_is_refused_with_a_clear_message(tmp_path):
    """A board running another protocol version: the device itself is the only fake here."""
    from firmware_bridge.codec import FrameDecoder, encode_frame

    master, slave = os.openpty()
    port = os.ttyname(slave)
    import threading

    stop = threading.Event()

    def old_firmware():
        decoder = FrameDecoder()
        os.set_blocking(master, False)
        while not stop.is_set():
            try:
                data = os.read(master, 256)
            except BlockingIOError:
                time.sleep(0.005)
                continue
            for frame in decoder.feed(data):
                if isinstance(frame.message, m.HelloRequest):
                    hello = m.Hello(protocol_hash=0xDEADBEEF, boot_id=1, fw_major=0, fw_minor=0)
                    os.write(master, encode_frame(hello, 0))

    thread = threading.Thread(target=old_firmware, daemon=True)
    thread.start()
    try:
        with pytest.raises(ProtocolMismatch) as info:
            BoardLink(port, handshake_timeout_s=2.0).open()
        text = str(info.value)
        assert "deadbeef" in text and f"{m.PROTOCOL_HASH:08x}" in text and "flash" in text
        assert "\n" not in text
    finally:
        stop.set()
        thread.join()
        os.close(slave)
        os.close(master)


def test_port_is_opened_exclusively(board, link):
    from firmware_bridge.link import PortUnavailable

    with pytest.raises(PortUnavailable, match="busy"):
        BoardLink(board.port).open()
