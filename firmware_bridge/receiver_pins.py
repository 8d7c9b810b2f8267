"""A hobby RC receiver's outputs, as edges into the C core: the simulator's receiver.

A receiver repeats each channel's pulse every 20 ms, the channels one after another. The
virtual board and the in-process link (virtual.py, direct.py) have no pins, so this plays the
receiver: given the widths the (simulated) transmitter asks for, it hands the core every edge
that is due, stamped with its own time (Timer1's 0.5 us count and the millisecond clock), just
as the board's pin-change interrupt does. The emulated AVR has real pins: avr_board.py drives
them through the emulator instead.
"""

from __future__ import annotations

from firmware_bridge.native import RC_SWITCH, RC_TICKS_PER_US, FirmwareCore

FRAME_US = 20_000
SLOT_US = (1_000, 3_500, 6_000)  # steering, throttle, switch: one after another in a frame


class ReceiverPins:
    """Three channels of pulses into `core` (nothing until the first `set`: no receiver)."""

    def __init__(self, core: FirmwareCore) -> None:
        self.core = core
        self.widths: tuple[int, int, int] | None = None
        self._next_frame_us: int | None = None
        self._edges: list[tuple[int, int, int]] = []  # (us, channel, level) still to come

    def set(self, steer_us: int, throttle_us: int, switch_us: int) -> None:
        """The widths from the next frame on (a frame under way keeps its own)."""
        self.widths = (int(steer_us), int(throttle_us), int(switch_us))

    def off(self) -> None:
        """The transmitter switched off: no more pulses after the frame under way."""
        self.widths = None

    def advance(self, now_us: int) -> None:
        """Hand the core every edge up to now_us, in order, then the time."""
        while True:
            if not self._edges:
                if self.widths is None:
                    self._next_frame_us = None
                    break
                if self._next_frame_us is None:
                    self._next_frame_us = now_us
                start = self._next_frame_us
                if start > now_us:
                    break
                for ch in range(RC_SWITCH + 1):
                    rise = start + SLOT_US[ch]
                    self._edges += [(rise, ch, 1), (rise + self.widths[ch], ch, 0)]
                self._edges.sort()
                self._next_frame_us = start + FRAME_US
            t, ch, level = self._edges[0]
            if t > now_us:
                break
            self._edges.pop(0)
            self.core.rc_edge(ch, level, t * RC_TICKS_PER_US, t // 1000)
        # every edge up to now handed over: as a board's loop() pass, the pulses that have
        # been quiet long enough count
        self.core.rc_settle(now_us * RC_TICKS_PER_US, now_us // 1000)
