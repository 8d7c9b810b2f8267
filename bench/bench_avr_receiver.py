"""The RC receiver's rules on the flashed binary, timed on the emulated ATmega328P.

Each trial drives the receiver pins (firmware_bridge/avr_emulator.py: pulse trains on D4-D6) and
measures in emulated cycles, from the falling edge of the first receiver pulse that carries the
change (the earliest moment the board can know it) to the rising edge of the first output pulse
that obeys it (the moment it reaches the servo or the ESC):

- take-over: in AUTO the steering stick leaves its deadzone → the servo pin carries the stick's
  width; with the host running, and with the host's process stopped (SIGSTOP) beforehand;
- e-stop: the switch channel to its e-stop position → neutral on the pins;
- loss: the transmitter goes silent → FAILSAFE (the ARMED LED goes dark), measured from the end
  of the last pulse; the rule says after RC_LOSS_MS.

The host is this module run with ``--host PORT`` (`host()` below), in its own process so that
the trials can freeze it. tests/test_avr_receiver.py runs the same
trials and asserts the bounds; `make bench` records the distributions.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from firmware_bridge import messages as m
from firmware_bridge.avr_emulator import F_CPU, AvrEmulator
from firmware_bridge.link import BoardLink, LinkError

REPO = Path(__file__).resolve().parents[1]
STEERING, THROTTLE, SWITCH = 0, 1, 2
RUN_WIDTHS = {STEERING: 1500, THROTTLE: 1500, SWITCH: 1000}  # sticks centred, switch at run
CYCLES_PER_MS = F_CPU / 1000
JITTER_US = 12.0  # fw_rc.h FW_RC_JITTER_US: how late an interrupt may stamp a receiver edge


@dataclass
class Trial:
    latency_ms: float  # cause (receiver pulse end) to the output pulse that obeys it
    first_error_us: float = 0.0  # that pulse's width minus the receiver's (edge-stamp jitter)
    width_error_us: float = 0.0  # passthrough once steady: output width minus the receiver's
    still_armed: bool | None = None  # take-over: the board still drives afterwards


class Rig:
    """An emulated board with a receiver on its pins and a host process that can be frozen."""

    def __init__(self, emu: AvrEmulator) -> None:
        self.emu = emu
        emu.rc_receiver(RUN_WIDTHS.values())
        time.sleep(0.2)  # five good frames: the receiver counts
        self.host = subprocess.Popen(
            [sys.executable, "-m", "bench.bench_avr_receiver", "--host", emu.port],
            cwd=REPO,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        line = self.host.stdout.readline().strip()
        if line != "armed":
            raise RuntimeError(f"the bench host did not arm: {line or self.host.poll()}")

    def tell(self, command: str) -> None:
        self.host.stdin.write(command + "\n")
        self.host.stdin.flush()
        reply = self.host.stdout.readline().strip()
        if reply != "ok":
            raise RuntimeError(f"the bench host answered {command!r} with {reply!r}")

    def resume_auto(self) -> None:
        """The policy drives again: the AUTO flag's 0 -> 1 edge releases a take-over."""
        self.tell("auto 0")
        time.sleep(0.05)
        self.tell("auto 1")
        time.sleep(0.05)

    def close(self) -> None:
        if self.host.poll() is None:
            os.kill(self.host.pid, signal.SIGCONT)
            try:
                self.tell("quit")
                self.host.wait(timeout=5)
            except (RuntimeError, OSError, subprocess.TimeoutExpired):
                self.host.kill()
                self.host.wait()


def _after(events, cycle: int, kind: str, accept=lambda e: True):
    return next((e for e in events if e.kind == kind and e.cycle > cycle and accept(e)), None)


def _latency(events, channel: int, out_kind: str, width_us: float, tolerance_us: float):
    """ms from the W event (the first receiver pulse with the change ended) to the rising edge
    of the first output pulse within tolerance_us of width_us, and that pulse's error."""
    cause = next(e for e in events if e.kind == "W" and e.value == channel)
    out = _after(
        events, cause.cycle, out_kind, lambda e: abs(e.value / 16 - width_us) <= tolerance_us
    )
    if out is None:
        raise AssertionError(f"no {out_kind} pulse of {width_us} us after the receiver's change")
    rise = out.cycle - out.value
    return (rise - cause.cycle) / CYCLES_PER_MS, out.value / 16 - width_us


def take_over(rig: Rig, rng: random.Random, *, frozen: bool) -> Trial:
    emu = rig.emu
    rig.resume_auto()
    if frozen:
        os.kill(rig.host.pid, signal.SIGSTOP)
    time.sleep(rng.uniform(0.0, 0.04))  # any phase against both 20 ms frames
    # past the deadzone (60 us), and away from the policy's 1600 us so that the change shows
    width = rng.choice([rng.randint(1000, 1430), rng.randint(1620, 2000)])
    emu.take_events()
    emu.rc_train(STEERING, width)
    time.sleep(0.25 if frozen else 0.08)  # frozen: past the host's 200 ms watchdog as well
    events = emu.take_events()
    steady_width_us = emu.pulses_us()[0]
    emu.rc_train(STEERING, RUN_WIDTHS[STEERING])
    if frozen:
        os.kill(rig.host.pid, signal.SIGCONT)
    latency, first = _latency(events, STEERING, "A", width, JITTER_US)
    steady = steady_width_us - width
    still = not any(e.kind == "L" and e.value == 0 for e in events)
    time.sleep(0.05)
    return Trial(latency, first, steady, still)


def switch_estop(rig: Rig, rng: random.Random) -> Trial:
    emu = rig.emu
    rig.resume_auto()  # the policy's 1600 us on the servo: neutral is a change
    time.sleep(rng.uniform(0.0, 0.04))
    emu.take_events()
    emu.rc_train(SWITCH, rng.randint(1700, 2000))
    time.sleep(0.06)
    events = emu.take_events()
    latency, _ = _latency(events, SWITCH, "A", 1500, 1.0)  # the servo back at its centre
    emu.rc_train(SWITCH, RUN_WIDTHS[SWITCH])
    time.sleep(0.05)
    rig.tell("rearm")
    return Trial(latency)


def signal_loss(rig: Rig, rng: random.Random) -> Trial:
    emu = rig.emu
    rig.resume_auto()
    time.sleep(rng.uniform(0.0, 0.04))
    emu.take_events()
    for ch in RUN_WIDTHS:
        emu.rc_off(ch)
    time.sleep(0.2)
    events = emu.take_events()
    first_lost = min((e for e in events if e.kind == "O"), key=lambda e: e.cycle)
    led = _after(events, first_lost.cycle, "L", lambda e: e.value == 0)
    latency = (led.cycle - first_lost.cycle) / CYCLES_PER_MS
    emu.rc_receiver(RUN_WIDTHS.values())
    time.sleep(0.15)  # five frames to count again
    rig.tell("rearm")
    return Trial(latency)


def trials(n: int = 100, seed: int = 0) -> dict[str, list[Trial]]:
    rng = random.Random(seed)
    with AvrEmulator() as emu:
        rig = Rig(emu)
        try:
            return {
                "take_over_host_running": [take_over(rig, rng, frozen=False) for _ in range(n)],
                "take_over_host_frozen": [take_over(rig, rng, frozen=True) for _ in range(n)],
                "switch_estop": [switch_estop(rig, rng) for _ in range(n)],
                "signal_loss": [signal_loss(rig, rng) for _ in range(n)],
            }
        finally:
            rig.close()


def summary(results: dict[str, list[Trial]]) -> dict:
    out = {}
    for name, runs in results.items():
        lat = sorted(t.latency_ms for t in runs)
        out[name] = {
            "trials": len(runs),
            "latency_ms_min": round(lat[0], 3),
            "latency_ms_median": round(lat[len(lat) // 2], 3),
            "latency_ms_max": round(lat[-1], 3),
            "first_pulse_error_us_max": round(max(abs(t.first_error_us) for t in runs), 3),
            "steady_width_error_us_max": round(max(abs(t.width_error_us) for t in runs), 3),
        }
        if runs[0].still_armed is not None:
            out[name]["still_armed"] = sum(bool(t.still_armed) for t in runs)
    return out


def run() -> dict:
    result = summary(trials())
    for name, s in result.items():
        print(
            f"   {name}: {s['trials']} trials, {s['latency_ms_min']:.2f} / "
            f"{s['latency_ms_median']:.2f} / {s['latency_ms_max']:.2f} ms (min / median / max)"
        )
    return result


POLICY = (0.2, 0.1)


def host(port: str) -> int:
    """The trials' host: opens the link, names the receiver as the person's controls, arms, lets
    the "policy" drive (AUTO flag, a new decision every 100 ms, steering +0.2 and throttle +0.1,
    so a neutral output is a visible change) and obeys one command per line on stdin: ``auto 0``
    / ``auto 1``, ``rearm`` (clear, then arm), ``quit``; each answered ``ok`` or ``error ...``;
    ``armed`` once it drives. The trials stop it with SIGSTOP to play a frozen host."""
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
    if len(sys.argv) != 3 or sys.argv[1] != "--host":
        sys.exit("usage: python -m bench.bench_avr_receiver --host PORT (the trials run it)")
    sys.exit(host(sys.argv[2]))
