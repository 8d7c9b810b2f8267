"""The firmware's CPU cost on its real target: cycles per received COMMAND frame on the
emulated ATmega328P (firmware_bridge/avr_emulator.py), and the load that is at 50 Hz each way.

Measured with the firmware's own busy pins in emulated cycles: D12 is high while fw_core_rx()
handles received bytes (COBS, CRC check, the COMMAND's state machine), D11 while fw_core_tick()
runs; its longest stretch is the tick that builds and queues a TELEMETRY frame. The UART's
receive interrupt (the Arduino core's, a few dozen cycles per byte) is not in either figure.
Ratio printed: the load at 50 Hz against the 16 MHz CPU.
"""

from __future__ import annotations

import time

import serial

from firmware_bridge import messages as m
from firmware_bridge.avr_emulator import F_CPU, AvrEmulator
from firmware_bridge.codec import encode_frame

RATE_HZ = 50.0


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
        rx, tick = emu.busy()
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


def run() -> dict:
    with AvrEmulator() as emu:
        result = command_frame_cost(emu)
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
    return result
