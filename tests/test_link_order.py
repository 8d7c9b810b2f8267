"""The link's frames reach the board in the order they were numbered, whoever sends them.

Three writers share one BoardLink: its 50 Hz sender thread, the control loop's `send_now` and an
e-stop from the joystick thread. The board side here is a bare pty that answers HELLO and
records every frame's sequence number, so an out-of-order frame is seen exactly as the firmware
would see it (an older AUTO flag after a newer one hands the wheels back to the receiver).
"""

from __future__ import annotations

import itertools
import os
import threading
import time

from firmware_bridge import messages as m
from firmware_bridge.codec import FrameDecoder, encode_frame
from firmware_bridge.link import BoardLink


class RecordingBoard:
    """The far end of a pty: answers HELLO, records (seq, message) of every other frame."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        self.port = os.ttyname(self.slave)
        self.frames: list[tuple[int, object]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        decoder = FrameDecoder()
        os.set_blocking(self.master, False)
        while not self._stop.is_set():
            try:
                data = os.read(self.master, 4096)
            except BlockingIOError:
                time.sleep(0.001)
                continue
            for frame in decoder.feed(data):
                if isinstance(frame.message, m.HelloRequest):
                    hello = m.Hello(protocol_hash=m.PROTOCOL_HASH, boot_id=7)
                    os.write(self.master, encode_frame(hello, 0))
                else:
                    self.frames.append((frame.seq, frame.message))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        os.close(self.slave)
        os.close(self.master)


def test_frames_from_three_threads_arrive_in_sequence_order():
    board = RecordingBoard()
    try:
        link = BoardLink(board.port, send_period_s=0.001).open()  # a busy sender thread
        try:
            go = threading.Event()

            def control_loop() -> None:
                go.wait()
                for i in range(1500):
                    link.set_auto(i % 2 == 0)
                    link.set_command(0.1, 0.2, send_now=True)

            def joystick_thread() -> None:
                go.wait()
                for _ in range(1500):
                    link.estop()

            threads = [threading.Thread(target=f) for f in (control_loop, joystick_thread)]
            for thread in threads:
                thread.start()
            go.set()
            for thread in threads:
                thread.join()
            time.sleep(0.1)  # the last frames through the pty
        finally:
            link.close()
    finally:
        board.close()
    seqs = [seq for seq, message in board.frames if isinstance(message, m.Command)]
    assert len(seqs) > 3000
    steps = [(b - a) & 0xFFFF for a, b in itertools.pairwise(seqs)]
    backwards = [i for i, step in enumerate(steps) if step == 0 or step >= 0x8000]
    assert not backwards, (
        f"{len(backwards)} of {len(steps)} frames reached the board after a newer one "
        f"(first at frame {backwards[0]}: seq {seqs[backwards[0]]} then {seqs[backwards[0] + 1]})"
    )
