"""`make demo`: carrt end to end on a laptop, no car needed, narrated.

Part 1: the built-in simulator driven by the policy this project trained (carrt/assets,
reproduced by `python training/demo_policy.py`), in real time through the full stack: the
10 Hz loop and arbitration, the C firmware core behind a pty with the real serial link, the
simulated camera on its own thread, the episode writer. It drives obstacle placements it never
saw in training; after a collision the car is reset and re-armed, as in the paper. The paper's
metrics are printed; the episodes, a video and a trajectory plot land in demo-out/.
Part 2: the safety link on the virtual board behind a real pty: e-stop, a hung control loop
and a pulled cable, and how the board stops the car each time.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from carrt.check import run_check
from carrt.shipped import SHIPPED_MODELS
from firmware_bridge import messages as m
from firmware_bridge.link import BoardLink
from firmware_bridge.link_types import LinkError
from firmware_bridge.virtual import VirtualBoard


def _drive(link: BoardLink, steering: float, throttle: float, seconds: float) -> float:
    """Act as a control loop for a while; return when its last decision went out."""
    end = time.monotonic() + seconds
    last = time.monotonic()
    while time.monotonic() < end:
        link.set_command(steering, throttle)
        last = time.monotonic()
        time.sleep(0.02)
    return last


def _wait(predicate, timeout_s: float = 2.0) -> float:
    start = time.monotonic()
    while not predicate() and time.monotonic() - start < timeout_s:
        time.sleep(0.001)
    return time.monotonic() - start


def _say(text: str) -> None:
    print(text, flush=True)


DEMO_POLICY = SHIPPED_MODELS["demo"]
HELD_OUT_TRACK = 101  # obstacle placement never used for the shipped policy's training data


def simulator_part(out: Path, seconds: float, model: Path = DEMO_POLICY) -> None:
    from carrt.cli import main as carrt
    from carrt.episodes.reader import iter_episodes

    episodes = out / "episodes"
    if episodes.is_dir():  # the demo's own output from a previous run: report this run only
        shutil.rmtree(episodes)
    who = "the shipped policy (trained by this project)" if model == DEMO_POLICY else str(model)
    _say(f"== the simulator: {who} drives")
    _say(f"   the 'hard' layout (8 obstacles, placement {HELD_OUT_TRACK}, not in its training")
    _say(f"   data) for {seconds:.0f} s in real time through the loop, the C core behind a pty")
    _say("   and the simulated camera, recording; a collision e-stops, resets and re-arms\n")
    code = carrt(
        ["drive", "--sim", "--autopilot", "--realtime", "--model", str(model), "--record",
         "--layout", "hard", "--track-seed", str(HELD_OUT_TRACK), "--duration", str(seconds),
         "--out", str(episodes), "--plot", str(out / "trajectory.png")]
    )  # fmt: skip
    if code != 0:
        raise SystemExit(code)
    recorded = [str(ep.path) for ep in iter_episodes(episodes)]
    carrt(["episodes", "video", *recorded, "-o", str(out / "run.mp4")])  # every episode, in order
    carrt(["report", str(episodes)])
    _say(f"\nwritten: {episodes}/, {out / 'run.mp4'} (all {len(recorded)} episodes, H.264), "
         f"{out / 'trajectory.png'}\n")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m carrt.demo", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--out", default="demo-out", help="output directory (default demo-out)")
    parser.add_argument("--seconds", type=float, default=40.0, help="simulator driving time")
    parser.add_argument("--model", default=str(DEMO_POLICY), help="policy to show (default: ours)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    simulator_part(out, args.seconds, Path(args.model))
    try:
        safety_link_part()
    except LinkError as exc:  # one line, not a traceback, should the link misbehave
        print(f"demo: the safety-link part failed: {exc}", file=sys.stderr)
        return 1
    _say(f"demo finished: outputs in {out}/")
    return 0


def safety_link_part() -> None:
    """The C firmware core behind a pty and the real host link: check, drive, e-stop, a hung
    loop, a pulled cable."""
    _say("== the safety link: the C firmware core behind a pty, the real host link\n")
    with VirtualBoard() as board, BoardLink(board.port) as link:
        _say(f"virtual board on {board.port} (C firmware core behind a pty)\n")
        _say("carrt check:")
        _say(run_check(link, pings=20, duration_s=0.5).render())

        _say("\ndriving: arm, then steering 0.3 and throttle 0.5 for 1.5 s")
        link.set_command(0.0, 0.0)
        link.wait_until_still()
        link.arm()
        start_ticks = link.telemetry.telemetry.encoder_ticks
        _drive(link, 0.3, 0.5, 1.5)
        tel = link.telemetry.telemetry
        _say(
            f"  board applies steering {tel.steer_us} us, throttle {tel.throttle_us} us; "
            f"wheel {board.plant.speed_mps:.2f} m/s, +{tel.encoder_ticks - start_ticks} ticks"
        )

        _say("\ne-stop from the host (sent at once, not at the next 20 ms tick)")
        t0 = time.monotonic()
        link.estop()
        took = _wait(lambda: board.state == m.State.ESTOP)
        _say(f"  board in ESTOP after {took * 1e3:.1f} ms, throttle {board.throttle_us} us")
        _drive(link, 0.3, 0.5, 0.3)
        _say(f"  still {board.state.name} while commands keep coming: latched")
        link.set_command(0.0, 0.0)
        link.clear()
        _say(f"  clear -> {board.state.name}; arming is a separate step")

        _say("\nthe control loop hangs (the link thread keeps sending the last decision)")
        link.wait_until_still()
        link.arm()
        t0 = _drive(link, 0.0, 0.3, 0.3)
        _wait(lambda: board.state == m.State.FAILSAFE)
        _say(
            f"  board {board.state.name} ({board.reason.name}) after "
            f"{(time.monotonic() - t0) * 1e3:.0f} ms without a new decision"
        )
        link.set_command(0.0, 0.0)
        link.clear()

        _say("\nthe USB cable is pulled while driving")
        link.wait_until_still()
        link.arm()
        _drive(link, 0.0, 0.4, 0.5)
        board.pull_cable()
        t0 = time.monotonic()
        _wait(lambda: board.state == m.State.FAILSAFE)
        _say(
            f"  board {board.state.name} ({board.reason.name}) "
            f"{(time.monotonic() - t0) * 1e3:.0f} ms after the pull, "
            f"throttle {board.throttle_us} us"
        )
        board.plug_cable()
        _wait(lambda: link.connected, timeout_s=3.0)
        _drive(link, 0.0, 0.4, 0.3)
        _say(
            f"  cable back: host reconnected ({link.counters.reconnects} reconnect), "
            f"board still {board.state.name}, throttle {board.throttle_us} us: "
            "it drives again only after clear and arm"
        )
        link.set_command(0.0, 0.0)
        link.clear()

        c = link.counters
        _say(
            f"\nlink counters: {c.frames_sent} frames sent, {c.frames_received} received, "
            f"{c.estops_sent} e-stop, {c.disconnects} disconnect, {c.reconnects} reconnect, "
            f"host drops {c.bad_crc + c.bad_length + c.overruns}"
        )


if __name__ == "__main__":
    raise SystemExit(main())
