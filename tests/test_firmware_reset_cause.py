"""The board's reset cause in HELLO, through the host link: the virtual board's power-on, its
reboots with a cause, its DTR reset when the port opens, and what the link makes of them
(BoardInfo.reset_cause) and says (messages.reset_cause_text). The flashed binary reading its
MCUSR on the emulated ATmega328P is in test_avr_emulated.py."""

from __future__ import annotations

import pytest
from e2e_rig import wait_for

from firmware_bridge import messages as m
from firmware_bridge.link import BoardInfo, BoardLink
from firmware_bridge.virtual import VirtualBoard


def test_each_reset_cause_has_its_words_and_anything_else_is_unknown():
    assert [(c.value, m.reset_cause_text(c)) for c in m.ResetCause] == [
        (0, "unknown"),
        (1, "power-on"),
        (2, "reset pin"),
        (3, "brown-out"),
        (4, "watchdog"),
    ]
    assert m.reset_cause_text(2) == "reset pin"  # the wire value as it comes
    assert m.reset_cause_text(5) == m.reset_cause_text(255) == "unknown"


def test_board_info_without_a_cause_says_unknown():
    info = BoardInfo(
        protocol_hash=1, boot_id=2, firmware_version=(0, 1, 0), config_from_storage=False
    )
    assert info.reset_cause == m.ResetCause.UNKNOWN


@pytest.mark.parametrize("cause", [m.ResetCause.BROWN_OUT, m.ResetCause.WATCHDOG])
def test_the_link_reports_why_the_virtual_board_last_started(cause):
    with VirtualBoard() as board, BoardLink(board.port) as link:
        assert link.board.reset_cause == m.ResetCause.POWER_ON
        assert isinstance(link.board.reset_cause, m.ResetCause)
        first = link.board.boot_id
        board.reboot(reset_cause=cause)  # the unprompted HELLO of the new boot
        wait_for(lambda: link.board.boot_id != first, timeout_s=2.0)
        assert link.board.reset_cause == cause
        board.reboot()  # a power cycle, by default
        wait_for(lambda: link.board.reset_cause == m.ResetCause.POWER_ON, timeout_s=2.0)


def test_a_board_reset_by_the_port_opening_says_reset_pin():
    """--reset-on-open plays an Arduino's DTR auto-reset: the reset pin, not a power-on."""
    with VirtualBoard(reset_on_open=True) as board:
        for _ in range(2):  # the first open, and one after the cable was pulled and plugged
            with BoardLink(board.port) as link:
                # the board may answer HELLO_REQUEST before it sees the port open: its power-on
                wait_for(lambda: link.board.reset_cause == m.ResetCause.EXTERNAL, timeout_s=2.0)
                assert m.reset_cause_text(link.board.reset_cause) == "reset pin"
            board.pull_cable()
            board.plug_cable()
        assert board.boot_count == 3
