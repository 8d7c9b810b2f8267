"""The firmware's CPU cost on its real target: cycles per received COMMAND frame on the
emulated ATmega328P (firmware_bridge/avr_emulator.py), and the load that is at 50 Hz each way.

Measured with the firmware's own busy pins in emulated cycles: D12 is high while fw_core_rx()
handles received bytes (COBS, CRC check, the COMMAND's state machine), D11 while fw_core_tick()
runs; its longest stretch is the tick that builds and queues a TELEMETRY frame. The UART's
receive interrupt (the Arduino core's, a few dozen cycles per byte) is not in either figure.
Ratio printed: the load at 50 Hz against the 16 MHz CPU.

Side by side: the same measurements of the firmware as it was before the RC receiver
(BASELINE_COMMIT, built from that commit's sources with the same toolchain), with its flash and
RAM use, so what the receiver costs is measured, not guessed. With a receiver's three channels
running, D8 is high while their edges, and the time for the pulses that wait for a quiet line,
are handed to the core (not the check each loop() pass makes whether anything is due); that is
reported too.
"""

from __future__ import annotations

import subprocess
import tempfile
import time
from pathlib import Path

import serial

from firmware_bridge import messages as m
from firmware_bridge.avr_emulator import F_CPU, FIRMWARE_ELF, REPO, AvrEmulator, build
from firmware_bridge.codec import encode_frame

RATE_HZ = 50.0
BASELINE_COMMIT = "41e5360"  # the last firmware without the RC receiver (issue 61)


def memory_use(elf: Path) -> dict:
    """Flash (.text + .data) and static RAM (.data + .bss + .noinit) of an AVR ELF, from
    avr-size."""
    out = subprocess.run(["avr-size", "-A", str(elf)], capture_output=True, text=True, check=True)
    sizes = {}
    for line in out.stdout.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].startswith(".") and parts[1].isdigit():
            sizes[parts[0]] = int(parts[1])
    data = sizes.get(".data", 0)
    return {
        "flash_bytes": sizes.get(".text", 0) + data,
        "ram_bytes": data + sizes.get(".bss", 0) + sizes.get(".noinit", 0),
    }


def baseline_elf(work: Path) -> Path:
    """The firmware of BASELINE_COMMIT, built from that commit's sources into `work`."""
    archive = subprocess.run(
        [
            "git",
            "-C",
            str(REPO),
            "archive",
            BASELINE_COMMIT,
            "Makefile",
            "firmware_bridge/firmware",
        ],
        capture_output=True,
        check=True,
    )
    subprocess.run(["tar", "-x", "-C", str(work)], input=archive.stdout, check=True)
    subprocess.run(["make", "-s", "-C", str(work), "firmware"], capture_output=True, check=True)
    return work / "build" / "firmware" / "carrt_fw.elf"


def command_frame_cost(emu: AvrEmulator, n_frames: int = 400) -> dict:
    """Send n COMMAND frames (2 ms apart, decision changing) and divide the rx busy time."""
    port = serial.Serial(emu.port, 250000, timeout=0)
    try:
        time.sleep(0.3)  # boot: HELLO, EEPROM, the first ticks
        emu.busy()  # start counting from here
        for i in range(n_frames):
            port.write(encode_frame(m.Command(i % 2000, 0, i + 1, 0), i & 0xFFFF))
            time.sleep(0.002)
            port.read(4096)  # keep the board's TELEMETRY flowing
        time.sleep(0.05)
        rx, tick, _ = emu.busy()
    finally:
        port.close()
    frame_bytes = len(encode_frame(m.Command(1, 0, 1, 0), 1))
    cycles_per_frame = rx.total / n_frames
    return {
        "frames": n_frames,
        "command_frame_bytes": frame_bytes,
        "rx_cycles_per_command_frame": round(cycles_per_frame, 1),
        "rx_us_per_command_frame": round(cycles_per_frame / (F_CPU / 1e6), 2),
        "rx_load_at_50hz": cycles_per_frame * RATE_HZ / F_CPU,
        "tick_cycles_mean": round(tick.total / max(tick.count, 1), 1),
        "tick_cycles_longest": tick.longest,
        "tx_load_at_50hz": tick.longest * RATE_HZ / F_CPU,
    }


def receiver_edge_cost(emu: AvrEmulator, seconds: float = 2.0) -> dict:
    """Cycles spent handing receiver edges and the time to the core (D8), three channels at
    50 Hz: six edges and three pulses that count per 20 ms frame."""
    emu.rc_receiver((1500, 1500, 1000))
    time.sleep(0.3)
    emu.busy()
    time.sleep(seconds)
    _, _, rc = emu.busy()
    per_edge = rc.total / max(rc.count, 1)  # a pass usually hands over one edge or one pulse
    return {
        "rc_cycles_per_edge_pass": round(per_edge, 1),
        "rc_load_at_50hz": rc.total / (seconds * F_CPU),
    }


def measure(elf: Path | None) -> dict:
    with AvrEmulator(elf) as emu:
        result = command_frame_cost(emu)
        result.update(receiver_edge_cost(emu))
    result.update(memory_use(elf or FIRMWARE_ELF))
    return result


def run() -> dict:
    build()
    result = measure(None)
    with tempfile.TemporaryDirectory(prefix="carrt-fw-baseline-") as work:
        before = measure(baseline_elf(Path(work)))
    result["baseline"] = {"commit": BASELINE_COMMIT, **before}
    result["ratio_to_baseline"] = {
        key: round(result[key] / before[key], 3)
        for key in (
            "flash_bytes",
            "ram_bytes",
            "rx_cycles_per_command_frame",
            "tick_cycles_longest",
        )
    }
    print(
        f"   COMMAND frame received ({result['command_frame_bytes']} bytes on the wire): "
        f"{result['rx_cycles_per_command_frame']:.0f} cycles "
        f"({result['rx_us_per_command_frame']:.1f} us at 16 MHz); at 50 Hz "
        f"{result['rx_load_at_50hz']:.3%} of the CPU"
    )
    print(
        f"   tick: mean {result['tick_cycles_mean']:.0f} cycles, longest (TELEMETRY out) "
        f"{result['tick_cycles_longest']} cycles; at 50 Hz {result['tx_load_at_50hz']:.3%}"
    )
    print(
        f"   receiver edges: {result['rc_cycles_per_edge_pass']:.0f} cycles per pass, "
        f"{result['rc_load_at_50hz']:.3%} of the CPU with three channels at 50 Hz"
    )
    b = result["baseline"]
    print(f"   {'':28} {'before ' + b['commit']:>16} {'now':>10} {'ratio':>7}")
    for key in result["ratio_to_baseline"]:
        print(f"   {key:28} {b[key]:>16} {result[key]:>10} {result['ratio_to_baseline'][key]:>7}")
    return result
