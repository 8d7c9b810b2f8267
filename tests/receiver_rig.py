"""The car's rig with the RC receiver as the person's controls, for the tests that drive through
a part's failure (tests/test_board_reboot.py, tests/test_fault_lines.py): the virtual board
behind a pty, read off as a scope would, and the person's transmitter as pulse widths."""

from __future__ import annotations

import time

from e2e_rig import wait_for

from firmware_bridge import messages as m
from firmware_bridge.virtual import VirtualBoard

NEUTRAL = (1500, 1500, 1000)  # steering, throttle, switch at run
GESTURE_S = 0.3
RELEASE_S = 0.3


class VirtualCar:
    """The virtual board, with the widths and state the tests read off it."""

    def __init__(self) -> None:
        self.board = VirtualBoard().start()
        self.port = self.board.port

    def set_receiver(self, *widths: int) -> None:
        self.board.set_receiver(*widths)

    def pulses(self) -> tuple[float, float]:
        return float(self.board.steer_us), float(self.board.throttle_us)

    def armed(self) -> bool:
        return self.board.state == m.State.ARMED

    def state(self) -> m.State:
        return self.board.state

    def reason(self) -> m.Reason:
        return self.board.reason

    def brown_out(self) -> None:
        """Rebooted in place: RAM and state gone, the port stays (a brown-out)."""
        self.board.reboot(reset_cause=m.ResetCause.BROWN_OUT)

    def restart_on_same_port(self) -> None:
        """Power off (the port goes), then a fresh board, defaults and all, on the same path."""
        port = self.port
        self.board.stop()
        time.sleep(0.3)
        self.board = VirtualBoard(port_path=port).start()
        self.set_receiver(*NEUTRAL)

    def switch_estops_on_the_board(self) -> None:
        """The transmitter's switch to e-stop: latched by the board's own receiver rule."""
        self.set_receiver(1500, 1500, 1900)
        wait_for(lambda: self.state() == m.State.ESTOP, timeout_s=1.0)
        assert self.reason() == m.Reason.RC_SWITCH, "latched by the board, not by the host"

    def close(self) -> None:
        self.board.stop()


class AvrCar:
    """The firmware binary on the emulated ATmega328P (firmware_bridge/avr_board.py), read off
    its pins: the pulse widths, and the ARMED LED's level from the emulator's events."""

    def __init__(self) -> None:
        from firmware_bridge.avr_board import AvrBoard

        self.board = AvrBoard().start()
        self.port = self.board.port
        self.emulator = self.board.emulator
        self._led = 0
        self._events: list = []

    def set_receiver(self, *widths: int) -> None:
        self.board.set_receiver(*widths)

    def pulses(self) -> tuple[float, float]:
        return self.emulator.pulses_us()

    def _take(self) -> list:
        events = self.emulator.take_events()
        for event in events:
            if event.kind == "L":
                self._led = event.value
        self._events.extend(events)
        return events

    def armed(self) -> bool:
        self._take()
        return self._led == 1

    def reset(self) -> None:
        """The reset pin (the emulator's reset: RAM and registers start over, EEPROM kept)."""
        self.emulator.reset()

    def switch_estops_on_the_board(self) -> None:
        """The switch to e-stop: the LED goes dark within a few ms of the switch's pulse in
        the board's own cycles; the host would need a telemetry frame and a tick (>= 20 ms)."""
        self._take()
        since = len(self._events)
        self.set_receiver(1500, 1500, 1900)
        wait_for(lambda: not self.armed(), timeout_s=1.0)
        events = self._events[since:]
        cause = next(e for e in events if e.kind == "W" and e.value == 2)
        dark = next(e for e in events if e.kind == "L" and e.value == 0 and e.cycle > cause.cycle)
        assert dark.t_s - cause.t_s < 0.005, "the board's own rule, within a few milliseconds"

    def close(self) -> None:
        self.board.stop()


def person_arms_and_gives_auto(car) -> None:
    """The transmitter: steering full right for the gesture, let go (arm), sticks let go (the
    receiver drove in MANUAL: the release gives the wheels to the policy)."""
    car.set_receiver(*NEUTRAL)
    time.sleep(0.5)  # the receiver valid on the board, the wheels still for 100 ms
    car.set_receiver(2000, 1500, 1000)
    time.sleep(GESTURE_S + 0.4)
    car.set_receiver(*NEUTRAL)
    wait_for(car.armed, timeout_s=3.0)
    wait_for(lambda: car.pulses()[1] > 1650, timeout_s=4.0)  # AUTO: the policy drives


def highest_throttle(car, seconds: float) -> float:
    top, end = 0.0, time.monotonic() + seconds
    while time.monotonic() < end:
        top = max(top, car.pulses()[1])
        time.sleep(0.005)
    return top
