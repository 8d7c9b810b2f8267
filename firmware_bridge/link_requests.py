"""The link's requests that wait for their answer: PING → PONG, CONFIG_REQUEST → CONFIG, and
CONFIG → CONFIG_ACK. A mixin of BoardLink (link.py), which owns the port and the receiving half
that routes each answer back here by its key."""

from __future__ import annotations

import os
from typing import Any

from firmware_bridge import messages as m
from firmware_bridge.codec import encode_frame
from firmware_bridge.link_types import LinkError


class Requests:
    """Needs the link's `receiver`, `port`, `clock`, `_next_seq()` and `_write()`."""

    receiver: Any
    port: str

    def ping(self, timeout_s: float = 0.5) -> float:
        """Round-trip time to the board in seconds (host → board → host)."""
        nonce = int.from_bytes(os.urandom(4), "little")
        start = self.clock()
        self._request(m.Ping(nonce=nonce), (m.Pong.TYPE, nonce), timeout_s)
        return self.clock() - start

    def read_config(self, timeout_s: float = 0.5) -> m.Config:
        return self._request(m.ConfigRequest(), (m.Config.TYPE, 0), timeout_s)

    def send_config(self, config: m.Config, timeout_s: float = 0.5) -> m.ConfigAck:
        return self._request(config, (m.ConfigAck.TYPE, None), timeout_s)

    def _request(self, message: Any, key: tuple[int, int | None], timeout_s: float) -> Any:
        seq = self._next_seq()
        if key[1] is None:  # answered by sequence number (CONFIG_ACK)
            key = (key[0], seq)
        event, box = self.receiver.expect(key)
        try:
            self._write(encode_frame(message, seq))
            if not event.wait(timeout_s):
                raise LinkError(
                    f"board on {self.port} did not answer {type(message).__name__} "
                    f"within {timeout_s * 1000:.0f} ms"
                )
            return box[0]
        finally:
            self.receiver.forget(key)
