"""A board that reboots under the host: how long until it has the car's CONFIG back.

The virtual board (the C core behind a pty) is rebooted in place while the host's link is
open and holding the car's config (`BoardLink.keep_config`, a throttle limit of 0.5 and the
receiver as the person's controls). Timed on the host's clock from the reboot to the board's
acknowledgement of the CONFIG the link sent again (`LinkCounters.configs_restored`), and the
config read back from the board afterwards is checked to be the car's. The ratio printed is
the worst time against the receiver's 100 ms validation after a boot (the board cannot be
re-armed from the transmitter sooner anyway).
"""

from __future__ import annotations

import statistics
import time

from firmware_bridge import messages as m
from firmware_bridge.link import BoardLink
from firmware_bridge.virtual import VirtualBoard

CAR_CONFIG = m.Config(max_forward=5000, controls=int(m.Controls.RECEIVER))
RECEIVER_VALIDATION_S = 0.1


def config_back_after_reboot(trials: int = 30) -> dict:
    times = []
    with VirtualBoard() as board, BoardLink(board.port) as link:
        assert link.keep_config(CAR_CONFIG).result == 0
        for _ in range(trials):
            restored = link.counters.configs_restored
            start = time.monotonic()
            board.reboot()
            while link.counters.configs_restored == restored:
                if time.monotonic() - start > 5.0:
                    raise RuntimeError("the rebooted board never got the car's config back")
                time.sleep(0.0005)
            times.append(time.monotonic() - start)
            back = link.read_config()
            assert (back.max_forward, back.controls) == (CAR_CONFIG.max_forward, 1), back
            time.sleep(0.05)
    times.sort()
    return {
        "trials": trials,
        "config_back_ms": {
            "min": times[0] * 1e3,
            "median": statistics.median(times) * 1e3,
            "max": times[-1] * 1e3,
        },
        "worst_vs_receiver_validation": times[-1] / RECEIVER_VALIDATION_S,
    }


def run() -> dict:
    result = config_back_after_reboot()
    t = result["config_back_ms"]
    print(
        f"   reboot → car's CONFIG acknowledged: {t['min']:.1f} / {t['median']:.1f} / "
        f"{t['max']:.1f} ms (min/median/max of {result['trials']}); worst ×"
        f"{result['worst_vs_receiver_validation']:.2f} of the receiver's 100 ms validation"
    )
    return result
