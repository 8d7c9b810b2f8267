"""The simulator as a rig for `carrt teleop --sim` and `carrt drive --sim`.

Real time: the simulated car is the plant of the virtual board (the C core behind a pty), the
camera renders on its own thread, and the real BoardLink talks over the pty — the full stack,
only the physical world replaced; the board is the row's (carrt/rig_table.py: the virtual board, or
the firmware on the emulated AVR). Simulated clock (the default when no person drives and no
live view watches): the same loop, arbitration and C core, with the link in-process
(DirectBoardLink) and time jumping ahead, so hours of driving take minutes.
"""

from __future__ import annotations

import contextlib
import json
import random
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from carrt.clock import SimClock, WallClock
from carrt.interfaces import Mode
from carrt.rig import Rig, RigKind, load, person_controls
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
        if not self._armed_once:  # the car waits to be armed: not drive time, and the first
            return collided  # lap is timed from the first driving tick, as the episode's is
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


@dataclass
class SimRun:
    """What a drive on the simulator measured (`DriveResult.rig`): the paper's metrics and the
    trajectory they were computed from."""

    metrics: Any  # carrt.sim.metrics.RunMetrics
    recorder: TrajectoryRecorder


def open_sim_rig(
    stack: contextlib.ExitStack,
    drive: Any,
    config: Any,
    *,
    driving: bool,
    kind: RigKind,
) -> Rig:
    """The simulator as a rig (a factory of carrt/rig_table.py), with `kind.board` as its board;
    `drive` (a carrt.session.DriveConfig) says the placement, who drives and how fast."""
    from carrt.sim.expert import ScriptedExpert
    from carrt.sim.render import Renderer
    from carrt.sim.world import SimWorld

    world = SimWorld(layout=drive.layout, seed=drive.track_seed)
    plant = SimPlant(world)
    scripted = drive.expert or drive.autopilot  # no person at the controls
    if not scripted and not drive.pad:
        from carrt.sim.keyboard import require_display

        require_display()  # before anything starts: a window nobody can see drives nothing
    # a person at the keys, or watching the live view, needs the car at the speed of life
    realtime = drive.realtime or not scripted or drive.view is not None or kind.always_realtime
    if realtime:
        clock: Any = WallClock()
        board = load(kind.board)(plant).start()
        stack.callback(board.stop)
        link = BoardLink(board.port).open()
        where = f"in real time, {getattr(board, 'LABEL', kind.name)} on {board.port}"
    else:
        from firmware_bridge.direct import DirectBoardLink

        clock = SimClock(step_s=0.002)
        link = board = DirectBoardLink(plant, clock).open()
        where = "on the simulated clock"
    stack.callback(link.close)
    # The camera's phase against the loop's ticks is arbitrary on a real car: draw it per run.
    phase = random.Random(drive.seed).uniform(0.0, 1.0 / 30.0)
    camera = SimCamera(plant, Renderer(world.track), clock, realtime=realtime, phase_s=phase)
    camera.start()
    stack.callback(camera.stop)

    pilot = None
    if scripted:
        intervene = driving and drive.expert_intervene
        wants_expert = not driving or intervene
        expert = ScriptedExpert(world.track, world.params) if wants_expert else None
        pilot = SimPilot(
            plant,
            clock,
            expert=expert,
            engage_auto=driving,
            episodes=drive.episodes,
            # --episodes 2 alone must end: an expert that never crashes would otherwise drive
            # one endless episode (measured: 1,613 laps in 300 s of wall time)
            laps_per_episode=drive.laps if drive.laps or not drive.episodes else 1,
            random_start=drive.random_start,
            expert_noise=drive.expert_noise,
            expert_noise_tau=drive.expert_noise_tau,
            seed=drive.seed,
            intervene=intervene,
        )
        joystick: Any = pilot
    elif drive.pad:
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
    device = joystick
    if config.receiver.controls != "pad":
        # the device in the person's hand stands in for the transmitter: its sticks and buttons
        # become pulses on the board's receiver pins, read back like a real receiver's
        from carrt.receiver import RadioStandIn

        radio = RadioStandIn(device, board, config.receiver, clock.now)
        joystick = person_controls(
            config, link, clock, lambda: device, driving=driving, radio=radio
        )
        where += ", the person's controls through the board's RC receiver"
    tracker = Tracker(plant)
    return Rig(
        clock=clock,
        camera=camera,
        link=link,
        joystick=joystick,
        describe=f"simulator, layout {drive.layout} seed {drive.track_seed}, {where}",
        collisions=tracker.tick,
        follows_mode=[x for x in (pilot, tracker) if x is not None],
        watches_loop=[device] if hasattr(device, "status_source") else [],
        finish=lambda summary, out: _finish(drive, world, tracker, summary, out),
        simulated_time=not realtime,
    )


def _finish(drive: Any, world: Any, tracker: Tracker, summary: Any, out: Any) -> SimRun:
    """The paper's simulation metrics for this run, said on `out` (None: not said), saved with
    a plot under --out."""
    from carrt.sim import metrics
    from carrt.sim.runs import save_run

    del summary
    result = metrics.run_metrics(world.track, tracker.recorder)
    say = (lambda _line: None) if out is None else (lambda line: print(line, file=out))
    say(metrics.format_metrics(result))
    label = f"{drive.layout}-s{drive.track_seed}"
    if drive.out:
        folder = Path(drive.out)
        path = save_run(folder, world.track, tracker.recorder, result, label)
        (folder / "sim_metrics.json").write_text(json.dumps(asdict(result), indent=2) + "\n")
        say(f"run saved: {path} (and its .png trajectory plot)")
    if drive.plot:
        a = tracker.recorder.arrays()
        metrics.plot_trajectory(
            world.track, a["x"], a["y"], a["collision"], drive.plot, title=label, speeds=a["speed"]
        )
        say(f"trajectory plot: {drive.plot}")
    return SimRun(result, tracker.recorder)
