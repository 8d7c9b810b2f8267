"""A host for the receiver timing trials, in its own process so that the trials can freeze it.

Run as ``python -m bench.avr_rc_host PORT``: it opens the link to the emulated board, names the
receiver as the person's controls, arms, lets the "policy" drive (AUTO flag, a new decision every
100 ms, steering +0.2 and throttle +0.1, so a neutral output is a visible change) and then obeys
one command per line on stdin: ``auto 0`` / ``auto 1`` (the AUTO flag), ``rearm`` (clear, then
arm), ``quit``. It answers each with a line (``ok`` or ``error ...``) and prints ``armed`` once
it is driving. The trials stop it with SIGSTOP to play a frozen host.
"""

from __future__ import annotations

import sys
import threading

from firmware_bridge import messages as m
from firmware_bridge.link import BoardLink, LinkError

POLICY = (0.2, 0.1)


def main(port: str) -> int:
    link = BoardLink(port).open()
    stop = threading.Event()

    def decide() -> None:
        while not stop.wait(0.1):
            link.set_command(*POLICY)

    try:
        ack = link.send_config(m.Config(controls=int(m.Controls.RECEIVER)))
        if ack.result != m.ConfigResult.ACCEPTED:
            print(f"error config refused ({ack.result})", flush=True)
            return 1
        link.set_command(0.0, 0.0)
        link.wait_until_still()
        link.arm()
        link.set_auto(True)
        link.set_command(*POLICY)
        threading.Thread(target=decide, daemon=True).start()
        print("armed", flush=True)
        for line in sys.stdin:
            word = line.split()
            try:
                if word == ["auto", "0"] or word == ["auto", "1"]:
                    link.set_auto(word[1] == "1")
                    link.set_command(*POLICY, send_now=True)
                elif word == ["rearm"]:
                    link.clear()
                    link.set_command(0.0, 0.0)
                    link.arm()
                    link.set_command(*POLICY)
                elif word == ["quit"]:
                    print("ok", flush=True)
                    break
                else:
                    print(f"error unknown: {line.strip()}", flush=True)
                    continue
            except LinkError as exc:
                print(f"error {exc}", flush=True)
                continue
            print("ok", flush=True)
    finally:
        stop.set()
        link.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
