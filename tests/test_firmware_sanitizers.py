"""The firmware core under AddressSanitizer and UndefinedBehaviorSanitizer.

An out-of-bounds write or a signed overflow on the board shows up as a glitch, not a crash;
here the same C code is built with -fsanitize=address,undefined and driven hard (random bytes,
random and corrupted frames, arming and driving, configs, reboots, long tick runs, clock
jumps). The ASan runtime must be the first library in a process, so the driver runs in a child
Python started with LD_PRELOAD=libasan.so; this file is that driver when run as a script.
A canary run (a deliberate overflow through the harness) proves the sanitizer is really live.
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
REPORT_MARKERS = ("AddressSanitizer", "runtime error", "UndefinedBehaviorSanitizer")


def _asan_runtime() -> str | None:
    try:
        out = subprocess.run(
            ["gcc", "-print-file-name=libasan.so"], capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return out if os.path.isabs(out) and os.path.exists(out) else None


def _run_driver(mode: str) -> subprocess.CompletedProcess:
    from firmware_bridge.native import build_sanitized_library

    build_sanitized_library()  # compile errors surface here, not inside the child
    env = dict(os.environ)
    env.update(
        LD_PRELOAD=_asan_runtime() or "",
        ASAN_OPTIONS="detect_leaks=0:abort_on_error=0:exitcode=23",
        UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1:exitcode=24",
        PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")])),
    )
    return subprocess.run(
        [sys.executable, __file__, mode],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=env,
        timeout=120,
        check=False,
    )


needs_asan = pytest.mark.skipif(_asan_runtime() is None, reason="gcc has no libasan")


@needs_asan
def test_core_is_clean_under_asan_and_ubsan():
    result = _run_driver("drive")
    report = result.stdout + result.stderr
    assert result.returncode == 0, report[-4000:]
    assert "DRIVER OK" in result.stdout
    assert not any(marker in report for marker in REPORT_MARKERS), report[-4000:]


@needs_asan
def test_the_sanitizer_is_live():
    result = _run_driver("canary")
    assert result.returncode != 0
    assert "AddressSanitizer" in result.stderr, result.stderr[-2000:]


# ------------------------------------------------------------------ the driver (child process)


def _random_message(rng: random.Random, m) -> object:
    cls = rng.choice(m.MESSAGES)
    values = []
    for _, kind, _ in m.fields_of(cls):
        bits = 8 * m.KINDS[kind][1]
        lo = -(1 << (bits - 1)) if m.KINDS[kind][2] else 0
        values.append(rng.randint(lo, lo + (1 << bits) - 1))
    return cls(*values)


def _random_config(rng: random.Random, m) -> object:
    us = [rng.randint(700, 2300) for _ in range(6)]
    if rng.random() < 0.7:  # mostly plausible, so configs are also applied and persisted
        us = sorted(us[:3]) + sorted(us[3:])
        if rng.random() < 0.5:
            us[0], us[2] = us[2], us[0]
    limits = [rng.randint(0, 10001), rng.randint(0, 10001), rng.randint(0, 1000001)]
    receiver = [rng.randint(0, 3), *(rng.randint(700, 2300) for _ in range(2))]
    receiver += [rng.randint(0, 600), rng.randint(700, 2300)]  # deadzone, e-stop threshold
    return m.Config(*us, *limits, rng.randint(0, 1), *receiver)


def _corrupt(rng: random.Random, wire: bytes) -> bytes:
    wire = bytearray(wire)
    choice = rng.random()
    if choice < 0.4:
        wire[rng.randrange(len(wire))] ^= 1 << rng.randrange(8)
    elif choice < 0.7:
        del wire[rng.randrange(len(wire)) :]
    else:
        wire[rng.randrange(len(wire)) : rng.randrange(len(wire))] = rng.randbytes(
            rng.randint(1, 90)
        )
    return bytes(wire)


def drive(seed: int = 1, rounds: int = 2000) -> None:
    from firmware_bridge import codec
    from firmware_bridge import messages as m
    from firmware_bridge.native import FirmwareCore

    rng = random.Random(seed)
    core = FirmwareCore(sanitize=True)
    now = rng.choice([0, 0xFFFFF000])
    core.boot(rng.getrandbits(32), now, rng.randrange(256))
    seq = encoder = 0
    seen = set()

    def send(message: object, corrupt: bool = False) -> None:
        nonlocal seq
        wire = codec.encode_frame(message, seq)
        seq = (seq + 1) & 0xFFFF
        core.feed(_corrupt(rng, wire) if corrupt else wire, now)

    for _ in range(rounds):
        roll = rng.random()
        if roll < 0.2:
            core.feed(rng.randbytes(rng.randint(0, 300)), now)
        elif roll < 0.45:
            message = _random_config(rng, m) if rng.random() < 0.2 else _random_message(rng, m)
            send(message, corrupt=rng.random() < 0.3)
        elif roll < 0.75:  # an arming and driving episode with 1 ms ticks
            decision = rng.getrandbits(32)
            arm_at = rng.randint(90, 130)
            period = rng.choice([1, 5, 20, 50])
            receiver = rng.random() < 0.6  # a receiver on the pins: its pulses, and noise
            for step in range(rng.randint(50, 700)):
                now += 1
                if receiver and step % 20 == 0:  # a frame: three pulses, mostly plausible
                    for ch in range(3):
                        rise = now * 1000 + 1000 + 2500 * ch
                        width = (
                            rng.randint(900, 2100) if rng.random() < 0.9 else rng.randint(1, 5000)
                        )
                        core.rc_edge(ch, 1, rise * 2, rise // 1000)
                        core.rc_edge(ch, 0, (rise + width) * 2, (rise + width) // 1000)
                if receiver and rng.random() < 0.05:
                    core.rc_edge(rng.randrange(4), rng.randint(0, 1), rng.getrandbits(32), now)
                if receiver and rng.random() < 0.5:  # the time, now and then a wild one
                    ticks = now * 2000 if rng.random() < 0.9 else rng.getrandbits(32)
                    core.rc_settle_due(ticks)
                    core.rc_settle(ticks, now)
                if receiver and rng.random() < 0.01:  # the board's edge queue overflowed
                    core.rc_overflow(rng.getrandbits(8), now)
                if step > arm_at and rng.random() < 0.3:
                    encoder += rng.randint(-3, 5)
                    core.set_encoder(encoder)
                if step % period == 0 or step == arm_at:
                    flags = m.CommandFlags.ARM if step >= arm_at else 0
                    if rng.random() < 0.01:
                        flags = rng.randint(0, 255)
                    decision += rng.random() < 0.95
                    throttle = rng.randint(-12000, 12000) if step > arm_at else 0
                    steering = rng.randint(-32768, 32767)
                    send(m.Command(steering, throttle, decision & 0xFFFFFFFF, flags))
                core.tick(now)
                seen.add(core.state)
        elif roll < 0.85:  # clock jumps, including half and full turns of the 32-bit clock
            for _ in range(rng.randint(1, 50)):
                now += rng.choice([0, 1, 1, 1, 7, 20, 199, 200, 5000, 0x7FFFFFFF, 0xFFFFFFFF])
                core.tick(now)
        elif roll < 0.9:  # a long quiet stretch: telemetry fills the TX buffer
            for _ in range(rng.randint(100, 4000)):
                now += 1
                core.tick(now)
        elif roll < 0.95:
            core.storage = rng.randbytes(rng.randint(0, 40)) if rng.random() < 0.3 else core.storage
            core.boot(rng.getrandbits(32), now, rng.randrange(256))
            encoder = 0
        if rng.random() < 0.3:
            core.take_output()
        _ = (core.state, core.reason, core.arm_refusal, core.counters, core.steer_us)
        _ = (core.rc_drives, [core.rc_width_us(ch) for ch in range(4)])
    print("DRIVER OK", core.counters, sorted(seen), flush=True)


def canary() -> None:
    import ctypes

    from firmware_bridge.native import load_library

    lib = load_library(sanitize=True)
    handle = ctypes.create_string_buffer(lib.fwh_size())
    lib.fwh_create(handle)
    too_small = ctypes.create_string_buffer(1024)  # malloc'd: ASan guards its edges
    lib.fwh_storage_set(handle, ctypes.cast(too_small, ctypes.POINTER(ctypes.c_uint8)))
    lib.fwh_boot(handle, 1, 1, 0)
    for t in range(0, 2000, 20):
        lib.fwh_tick(handle, t)
    lib.fwh_tx_take(handle, ctypes.cast(too_small, ctypes.POINTER(ctypes.c_uint8)), 8192)
    print("canary survived: the sanitizer is not active", flush=True)


if __name__ == "__main__":
    {"drive": drive, "canary": canary}[sys.argv[1]]()
