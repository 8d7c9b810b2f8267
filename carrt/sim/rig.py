"""The simulator as a rig for `carrt teleop --sim` and `carrt drive --sim`.

Real time: the simulated car is the plant of the virtual board (the C core behind a pty), the
camera renders on its own thread, and the real BoardLink talks over the pty — the full stack,
only the physical world replaced. Simulated clock (the default when no person drives): the
same loop, arbitration and C core, with the link in-process (DirectBoardLink) and time jumping
ahead, so hours of driving take minutes.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import random
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from carrt.clock import SimClock, WallClock
from carrt.interfaces import Mode
from carrt.rig import Rig
from carrt.sim.camera import SimCamera
from carrt.sim.metrics import TrajectoryRecorder
from carrt.sim.pilot import SimPilot
from carrt.sim.plant import SimPlant
from carrt.sim.world import StepInfo
from firmware_bridge.link import BoardLink


@dataclass
class Tracker:
    """Samples the car once per control tick into the metrics' TrajectoryRecorder."""

    plant: SimPlant
    recorder: TrajectoryRecorder = field(default_factory=TrajectoryRecorder)
    mode_source: Any = None  # the loop's mode: time stopped after a crash is reset time
    _laps: int = 0
    _armed_once: bool = False
    _last_mode: Mode = Mode.DISARMED

    def tick(self) -> bool:
        """Record this tick; report (once) whether the car collided since the last tick."""
        collided = self.plant.take_collision()
        mode = self.mode_source() if self.mode_source is not None else Mode.MANUAL
        driving = mode in (Mode.MANUAL, Mode.AUTO)
        self._armed_once = self._armed_once or driving
        # a takeover: the person moved the sticks in AUTO and the arbiter handed over
        took_over = self._last_mode == Mode.AUTO and mode == Mode.MANUAL
        self._last_mode = mode
        with self.plant.lock:
            world = self.plant.world
            lap = world.laps > self._laps
            self._laps = world.laps
            info = StepInfo(collision=collided, collided_with="", lap_completed=lap)
            self.recorder.record(
                world, info, resetting=self._armed_once and not driving, intervention=took_over
            )
        return collided


def open_sim_rig(
    stack: contextlib.ExitStack, args: argparse.Namespace, config: Any, *, driving: bool
) -> Any:
    from carrt.sim.expert import ScriptedExpert
    from carrt.sim.render import Renderer
    from carrt.sim.world import SimWorld

    world = SimWorld(layout=args.layout, seed=args.track_seed)
    plant = SimPlant(world)
    scripted = getattr(args, "expert", None) == "auto" or getattr(args, "autopilot", False)
    if not scripted and not getattr(args, "pad", False):
        from carrt.sim.keyboard import require_display

        require_display()  # before anything starts: a window nobody can see drives nothing
    realtime = args.realtime or not scripted
    if realtime:
        from firmware_bridge.virtual import VirtualBoard

        clock: Any = WallClock()
        board = VirtualBoard(plant).start()
        stack.callback(board.stop)
        link = BoardLink(board.port).open()
        where = f"in real time, virtual board on {board.port}"
    else:
        from firmware_bridge.direct import DirectBoardLink

        clock = SimClock(step_s=0.002)
        link = DirectBoardLink(plant, clock).open()
        where = "on the simulated clock"
    stack.callback(link.close)
    # The camera's phase against the loop's ticks is arbitrary on a real car: draw it per run.
    phase = random.Random(args.seed).uniform(0.0, 1.0 / 30.0)
    camera = SimCamera(plant, Renderer(world.track), clock, realtime=realtime, phase_s=phase)
    camera.start()
    stack.callback(camera.stop)

    pilot = None
    if scripted:
        intervene = driving and getattr(args, "expert_intervene", False)
        wants_expert = not driving or intervene
        expert = ScriptedExpert(world.track, world.params) if wants_expert else None
        pilot = SimPilot(
            plant,
            clock,
            expert=expert,
            engage_auto=driving,
            episodes=args.episodes,
            # --episodes 2 alone must end: an expert that never crashes would otherwise drive
            # one endless episode (measured: 1,613 laps in 300 s of wall time)
            laps_per_episode=args.laps if args.laps or not args.episodes else 1,
            random_start=getattr(args, "random_start", False),
            expert_noise=getattr(args, "expert_noise", 0.0),
            seed=args.seed,
            intervene=intervene,
        )
        joystick: Any = pilot
    elif getattr(args, "pad", False):
        from carrt.joystick import PygameJoystick

        joystick = PygameJoystick(config.joystick)
    else:
        from carrt.sim.keyboard import KeyboardPad
        from carrt.sim.render import top_down

        joystick = KeyboardPad(
            plant,
            camera,
            renderer_map=lambda p: top_down(world.track, poses=[p.pose()]),
            max_throttle=config.joystick.max_throttle,
        )
    tracker = Tracker(plant)
    return Rig(
        clock=clock,
        camera=camera,
        link=link,
        joystick=joystick,
        describe=f"simulator, layout {args.layout} seed {args.track_seed}, {where}",
        collisions=tracker.tick,
        follows_mode=[x for x in (pilot, tracker) if x is not None],
        watches_loop=[joystick] if hasattr(joystick, "status_source") else [],
        finish=lambda summary: _finish(args, world, tracker, summary),
    )


def _finish(args: argparse.Namespace, world: Any, tracker: Tracker, summary: Any) -> None:
    """Print the paper's simulation metrics for this run; save them with a plot under --out."""
    from carrt.sim import metrics
    from carrt.sim.runs import save_run

    del summary
    result = metrics.run_metrics(world.track, tracker.recorder)
    on_metrics = getattr(args, "on_metrics", None)  # `carrt eval` collects, it does not print
    if on_metrics is not None:
        on_metrics(result, tracker.recorder)
    else:
        print(metrics.format_metrics(result))
    label = f"{args.layout}-s{args.track_seed}"
    if getattr(args, "out", None):
        out = Path(args.out)
        path = save_run(out, world.track, tracker.recorder, result, label)
        (out / "sim_metrics.json").write_text(json.dumps(asdict(result), indent=2) + "\n")
        print(f"run saved: {path} (and its .png trajectory plot)")
    if args.plot:
        a = tracker.recorder.arrays()
        metrics.plot_trajectory(
            world.track, a["x"], a["y"], a["collision"], args.plot, title=label, speeds=a["speed"]
        )
        print(f"trajectory plot: {args.plot}")
