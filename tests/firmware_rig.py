"""One board on the bench for the firmware core's tests: the real C core, a fake clock, and the
host's side of the wire.

The safety rules (test_firmware_core.py), the outputs under each configuration
(test_firmware_core_config.py) and the wire (test_firmware_core_wire.py) all drive the core
through the same `Bench`, with every time an explicit millisecond value.
"""

from __future__ import annotations

from hypothesis import settings

from firmware_bridge import codec
from firmware_bridge import messages as m
from firmware_bridge.messages import State
from firmware_bridge.native import FirmwareCore

ARM = m.CommandFlags.ARM
PROPS = settings(max_examples=200, deadline=None, derandomize=True)


class Bench:
    """One board on the bench: the C core, a fake clock, and the host's side of the wire."""

    def __init__(self, *, now: int = 0, boot_id: int = 0xB007) -> None:
        self.core = FirmwareCore()
        self.now = now
        self.seq = 0
        self.decision = 0
        self.encoder = 0
        self.rolling = False  # wheels turning: the encoder advances every millisecond
        self.decoder = codec.FrameDecoder()
        self.core.boot(boot_id, now)

    def send(self, message: object) -> None:
        self.core.feed(codec.encode_frame(message, self.seq), self.now)
        self.seq = (self.seq + 1) & 0xFFFF

    def command(self, steering=0, throttle=0, flags=0, decision_id=None) -> None:
        if decision_id is None:
            self.decision += 1
            decision_id = self.decision
        self.send(m.Command(steering, throttle, decision_id & 0xFFFFFFFF, flags))

    def set_encoder(self, ticks: int) -> None:
        self.encoder = ticks
        self.core.set_encoder(ticks)

    def run(self, ms: int, *, every: int | None = 20, **command) -> None:
        """Tick every millisecond for ms; a command goes out every `every` ms (None: silence)."""
        command.setdefault("flags", ARM)
        for i in range(1, ms + 1):
            self.now += 1
            if self.rolling:
                self.set_encoder(self.encoder + 1)
            if every and i % every == 0:
                self.command(**command)
            self.core.tick(self.now)

    def arm(self, throttle: int = 0) -> None:
        self.run(100, flags=0)  # wheels observed still for 100 ms, ARM low
        self.command(throttle=throttle, flags=ARM)
        assert self.core.state == State.ARMED, self.core.arm_refusal

    def frames(self, cls: type | None = None) -> list:
        got = self.decoder.feed(self.core.take_output())
        return [f for f in got if cls is None or isinstance(f.message, cls)]

    @property
    def neutral(self) -> bool:
        return (self.core.steer_us, self.core.throttle_us) == (1500, 1500)
