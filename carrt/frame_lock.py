"""The tick's phase lock to the camera: each 10 Hz tick runs when a frame arrives.

A loop on its own deadlines beside a free-running 30 fps camera uses a frame that is 0–33 ms
old (measured: frame → command p50 24.7 ms with inference ~2 ms). openpilot runs its model on
frame arrival instead; so does this loop. Each tick has a nominal deadline on a 10 Hz grid.
The loop waits, from half a frame period before the deadline, for the first frame captured
after that; the tick starts as soon as it arrives, so the command leaves a few milliseconds
after the frame. If no frame comes within the window (a stalled or slow camera), the tick
runs at the window's end on the newest frame it has, and the arbiter judges that frame's age
as before: the lock never waits longer than a frame period and never stops the loop.

The grid keeps 10 Hz on average whatever the camera's rate; it is pulled halfway towards the
frame that started each tick (a first-order phase-locked loop), so with a camera whose rate
is a multiple of 10 Hz the frames settle onto the deadlines and ticks are evenly spaced.
The simulator's camera has the same contract on the simulated clock, so simulated drives see
the same frame ages as the car.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

from carrt.interfaces import Camera, CameraFrame, Clock


@dataclass(frozen=True)
class Trigger:
    """Why a tick started when it did."""

    at: float  # the moment the tick started, on the loop's clock
    frame_at: float | None  # capture time of the frame that started it; None: window timed out


@dataclass
class FrameLock:
    """The 10 Hz grid and its window around each deadline, locked to the camera's frames."""

    period: float  # the tick period (0.1 s)
    frame_period: float  # the camera's nominal frame period (1/fps)
    gain: float = 0.5  # how far each frame pulls the grid towards itself

    def opens(self, deadline: float) -> float:
        """A frame captured from here on may start the tick due at `deadline`."""
        return deadline - 0.5 * self.frame_period

    def closes(self, deadline: float) -> float:
        """No frame by here: the tick runs anyway (a frame period after the window opens, plus
        a quarter for capture jitter)."""
        return deadline + 0.75 * self.frame_period

    def wait(self, clock: Clock, camera: Camera, deadline: float) -> Trigger:
        """Sleep to the window, then until a frame captured inside it arrives (or it closes)."""
        opens = self.opens(deadline)
        clock.sleep_until(opens)
        frame = camera.latest()
        if not _inside(frame, opens):
            camera.wait_newer(-1 if frame is None else frame.seq, self.closes(deadline))
            frame = camera.latest()
        frame_at = frame.captured_at if _inside(frame, opens) else None
        return Trigger(at=clock.now(), frame_at=frame_at)

    def lateness(self, trigger: Trigger, deadline: float) -> float:
        """How long after its frame (or after the window closed without one) the tick started:
        the loop's tick lateness."""
        due = trigger.frame_at if trigger.frame_at is not None else self.closes(deadline)
        return max(0.0, trigger.at - due)

    def next_deadline(self, deadline: float, trigger: Trigger) -> float:
        if trigger.frame_at is None:
            return deadline + self.period
        return deadline + self.period + self.gain * (trigger.frame_at - deadline)

    def realign(self, deadline: float, now: float) -> tuple[float, bool]:
        """After a tick: a tick that ran into the next window is an overrun; the grid skips to
        the next slot whose window is still ahead instead of bursting to catch up."""
        late = now - self.opens(deadline)
        if late <= 0:
            return deadline, False
        return deadline + (math.floor(late / self.period) + 1) * self.period, True


def _inside(frame: CameraFrame | None, opens: float) -> bool:
    return frame is not None and frame.captured_at >= opens


class NewFrameSignal:
    """For a camera with a capture thread: the thread announces each frame, the loop's thread
    waits for one without polling (a condition variable, so the tick starts within a scheduler
    wake-up of the frame, not a polling interval)."""

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._seq = -1

    def announce(self, seq: int) -> None:
        with self._condition:
            self._seq = seq
            self._condition.notify_all()

    def wait_newer(self, seq: int, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        with self._condition:
            while self._seq <= seq:
                remaining = end - time.monotonic()
                if remaining <= 0:
                    return
                self._condition.wait(remaining)
