"""The RC receiver's rules on the flashed binary, timed on the emulated ATmega328P.

Each trial drives the receiver pins (firmware_bridge/avr_emulator.py: pulse trains on D4-D6) and
measures in emulated cycles, from the falling edge of the first receiver pulse that carries the
change (the earliest moment the board can know it) to the rising edge of the first output pulse
that obeys it (the moment it reaches the servo or the ESC):

- take-over: in AUTO the steering stick leaves its deadzone → the servo pin carries the stick's
  width; with the host running, and with the host's process stopped (SIGSTOP) beforehand;
- e-stop: the switch channel to its e-stop position → neutral on the pins;
- loss: the transmitter goes silent → FAILSAFE (the ARMED LED goes dark), measured from the end
  of the last pulse; the rule says after RC_LOSS_MS;
- noise bursts (`noise_burst`): glitches on one receiver line or all three around the falling
  edge of one of its pulses, with the receiver driving and with the host driving; every output
  pulse after it must be the command on the pins or neutral (never a third width), and how
  often the board went neutral is counted.

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


# Noise bursts: glitches on the receiver's lines (AvrEmulator.rc_burst) on top of its pulses.
# "sparse": edges 20-90 us apart, the bursts a tester saw move the servo and the ESC with the
# firmware of before; "dense": a few us apart, faster than the pin-change interrupt comes
# (edges merge); "storm": as dense, for 8-12 ms on all three lines, more than the board's edge
# queue holds. Each: (shortest, longest gap in us, fewest, most edges).
BURSTS = {
    "sparse": (20.0, 90.0, 10, 60),
    "dense": (2.0, 6.0, 60, 300),
    "storm": (2.0, 6.0, 2000, 3000),
}
ALL_LINES = (STEERING, THROTTLE, SWITCH)
LINE_NAMES = ("steering", "throttle", "switch")
BURST_LINES = ((STEERING,), (THROTTLE,), (SWITCH,), ALL_LINES)
TAKE_OVER_WIDTHS = {STEERING: 1700, THROTTLE: 1430, SWITCH: 1000}  # reverse: no stall rule
NEUTRAL_US = 1500.0
BURST_TOLERANCE_US = 3.0  # the passthrough's 2 us (steady) plus one timer count


@dataclass
class BurstTrial:
    lines: tuple[int, ...]
    gaps: str  # a key of BURSTS
    receiver_drives: bool  # the take-over's widths on the pins, else the host's command
    wrong_us: float  # the largest output pulse off both the command and neutral (0: none)
    neutral: bool  # the outputs went neutral (FAILSAFE: the receiver's signal was lost)


def _host_widths() -> tuple[float, float]:
    steer, throttle = POLICY  # the bench host's command, on the default config's endpoints
    return 1500.0 + 500.0 * steer, 1500.0 + 500.0 * throttle


def _drive_by(rig: Rig, receiver: bool) -> tuple[float, float]:
    """Armed, with the receiver's take-over or the host's command on the pins: those widths."""
    emu = rig.emu
    widths = TAKE_OVER_WIDTHS if receiver else RUN_WIDTHS
    for ch, width in widths.items():
        emu.rc_train(ch, width)
    time.sleep(0.05)  # the new widths read
    if not receiver:
        rig.resume_auto()  # the AUTO edge hands the wheels back to the host
    expect = (float(widths[STEERING]), float(widths[THROTTLE])) if receiver else _host_widths()
    deadline = time.monotonic() + 3.0
    while True:  # six output frames at the expected widths (the steadied passthrough)
        time.sleep(0.13)
        steer, throttle = emu.pulses_us()
        if max(abs(steer - expect[0]), abs(throttle - expect[1])) <= BURST_TOLERANCE_US:
            return expect
        if time.monotonic() > deadline:
            raise RuntimeError(f"the outputs did not settle at {expect}: {steer}, {throttle}")


def noise_burst(
    rig: Rig, rng: random.Random, *, lines: tuple[int, ...], gaps: str, receiver: bool
) -> BurstTrial:
    """One burst (on each of `lines` at once) at a random phase of the receiver's frame while
    the receiver or the host drives; every output pulse from then until 100 ms after it is
    checked against the command on the pins and neutral. A burst that made the board give up
    the receiver's signal (FAILSAFE) is followed by a re-arm."""
    emu = rig.emu
    expect = _drive_by(rig, receiver)
    gap_min, gap_max, edges_min, edges_max = BURSTS[gaps]
    emu.take_events()
    # around the falling edge of one of the receiver's pulses (the edge whose loss would
    # mis-time a width), starting up to a whole burst before it
    anchor = rng.choice((STEERING, THROTTLE, SWITCH))
    edges = rng.randint(edges_min, edges_max)
    before = rng.uniform(0.0, edges * (gap_min + gap_max) / 2)
    for ch in lines:
        emu.rc_burst(
            ch, edges, gap_min, gap_max, rng.randrange(1 << 30),
            rng.uniform(-before, 0.0) if len(lines) > 1 else -before, after_fall_of=anchor,
        )  # fmt: skip
    time.sleep(0.15)
    events = emu.take_events()
    ends = [e for e in events if e.kind == "E"]
    if len(ends) != len(lines):
        raise RuntimeError(f"a burst did not finish: {ends}")
    wrong = 0.0
    neutral = False
    for e in events:
        if e.kind in "AB":
            width = e.value / 16
            want = expect[0] if e.kind == "A" else expect[1]
            off = min(abs(width - want), abs(width - NEUTRAL_US))
            if off > BURST_TOLERANCE_US:
                wrong = max(wrong, off)
            neutral |= abs(width - NEUTRAL_US) <= BURST_TOLERANCE_US
    if any(e.kind == "L" and e.value == 0 for e in events) or neutral:
        for ch, width in RUN_WIDTHS.items():
            emu.rc_train(ch, width)
        time.sleep(0.2)  # five good frames: the receiver counts again
        rig.tell("rearm")
        neutral = True
    return BurstTrial(lines, gaps, receiver, wrong, neutral)


def burst_trials(rig: Rig, rng: random.Random, per_case: int) -> list[BurstTrial]:
    """per_case sparse and dense bursts on each line and on all three at once, and per_case
    storms on all three, with the receiver driving and with the host driving."""
    cases = [(gaps, lines) for gaps in ("sparse", "dense") for lines in BURST_LINES]
    cases.append(("storm", ALL_LINES))
    return [
        noise_burst(rig, rng, lines=lines, gaps=gaps, receiver=receiver)
        for receiver in (True, False)
        for gaps, lines in cases
        for _ in range(per_case)
    ]


def burst_summary(runs: list[BurstTrial]) -> dict:
    """Per kind of burst, with the receiver driving ("rx") and the host ("host"): how many,
    how many put a wrong width on an output, how many went neutral (FAILSAFE)."""
    out: dict = {}
    for t in runs:
        key = f"{'rx' if t.receiver_drives else 'host'}_{t.gaps}_" + (
            "all" if len(t.lines) > 1 else LINE_NAMES[t.lines[0]]
        )
        row = out.setdefault(key, {"bursts": 0, "wrong": 0, "neutral": 0, "wrong_us_max": 0.0})
        row["bursts"] += 1
        row["wrong"] += t.wrong_us > 0
        row["neutral"] += t.neutral
        row["wrong_us_max"] = max(row["wrong_us_max"], round(t.wrong_us, 3))
    return out


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


def noise_trials(per_case: int = 10, seed: int = 1, elf=None) -> list[BurstTrial]:
    """burst_trials on a fresh emulated board (elf: another firmware, e.g. an older one)."""
    with AvrEmulator(elf) as emu:
        rig = Rig(emu)
        try:
            return burst_trials(rig, random.Random(seed), per_case)
        finally:
            rig.close()


def run() -> dict:
    result = summary(trials())
    for name, s in result.items():
        print(
            f"   {name}: {s['trials']} trials, {s['latency_ms_min']:.2f} / "
            f"{s['latency_ms_median']:.2f} / {s['latency_ms_max']:.2f} ms (min / median / max)"
        )
    bursts = burst_summary(noise_trials())
    for name, row in bursts.items():
        print(
            f"   noise {name}: {row['bursts']} bursts, a wrong width on the outputs in "
            f"{row['wrong']}, neutral (FAILSAFE) in {row['neutral']}"
        )
    return {**result, "noise_bursts": bursts}


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
