"""The link's requests that wait for their answer: PING → PONG, CONFIG_REQUEST → CONFIG, and
CONFIG → CONFIG_ACK, and the car's CONFIG kept for every new boot of the board. A mixin of
BoardLink (link.py), which owns the port and the receiving half that routes each answer back
here by its key."""

from __future__ import annotations

import os
from typing import Any

from firmware_bridge import messages as m
from firmware_bridge.codec import encode_frame
from firmware_bridge.link_types import LinkError

CONFIG_RETRY_S = 0.1  # a rebooted board's CONFIG is sent again this often until acknowledged


class Requests:
    """Needs the link's `receiver`, `port`, `clock`, `counters`, `_state_lock` and `_send()`,
    and the restore state BoardLink.__init__ sets (`_car_config`, `_config_pending`, ...)."""

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
        keys: list[tuple[int, int]] = []
        waiter: list[Any] = []

        def frame(seq: int) -> bytes:  # numbered and written under the link's one lock
            full = (key[0], seq) if key[1] is None else key  # CONFIG_ACK: by sequence number
            keys.append(full)
            waiter.extend(self.receiver.expect(full))  # before the write: the answer is fast
            return encode_frame(message, seq)

        try:
            if not self._send(frame):
                raise LinkError(
                    f"board on {self.port} is not connected: {type(message).__name__} not sent"
                )
            if not waiter[0].wait(timeout_s):
                raise LinkError(
                    f"board on {self.port} did not answer {type(message).__name__} "
                    f"within {timeout_s * 1000:.0f} ms"
                )
            return waiter[1][0]
        finally:
            for full in keys:
                self.receiver.forget(full)

    # ------------------------------------------------------------------ the car's config
    def keep_config(self, config: m.Config, timeout_s: float = 0.5) -> m.ConfigAck:
        """Send the car's CONFIG now and again to every new boot of the board, before any other
        frame goes out to it (a brown-out or a USB power cycle would otherwise leave it on its
        defaults: full throttle, the receiver not the person's controls). Returns the ack."""
        ack = self.send_config(config, timeout_s)
        if ack.result == 0:
            with self._state_lock:
                self._car_config = config
        return ack

    @property
    def config_pending(self) -> bool:
        """A rebooted board has not yet acknowledged the car's CONFIG (no ARM goes out)."""
        return self._config_pending

    def _restore_config(self) -> None:
        """After a reboot: the car's CONFIG on the wire (again every 100 ms until the board
        acknowledges it), ahead of the command this call precedes."""
        if not self._config_pending:
            return
        restore, now = self._restore, self.clock()
        if restore is not None and restore[1].is_set():
            ack = restore[2][0]
            with self._state_lock:
                self._restore = None
                if ack.result == 0:
                    self._config_pending = False
                    self.config_restore_error = None
                    self.counters.configs_restored += 1
                    return
                self.config_restore_error = (
                    f"the board refused the car config (result {ack.result})"
                )
        elif restore is not None and now - restore[0] < CONFIG_RETRY_S:
            return
        config = self._car_config
        if config is None:
            return

        def frame(seq: int) -> bytes:
            if self._restore is not None:
                self.receiver.forget((m.ConfigAck.TYPE, self._restore_seq))
            self._restore_seq = seq
            self._restore = (now, *self.receiver.expect((m.ConfigAck.TYPE, seq)))
            return encode_frame(config, seq)

        self._send(frame)
