"""A drive as a function of its config: `run_session(DriveConfig(...))` assembles the parts, runs
the loop, always leaves the car stopped, and returns what the run did. `carrt teleop` and
`carrt drive` (their flags: carrt/session_cmd.py), `carrt eval`, `carrt-sim-data` and the
training loop's drives all call it.

Start-up order is chosen so that everything that can be wrong is found before the car can
move: config, then the model (validated and warmed up), then the camera (first frame), then
the board (handshake, calibration sent), and only then the joystick that can arm it. Whatever
ends the run (quit, Ctrl-C, SIGTERM, an exception) goes through the same shutdown: disarm,
neutral command, episode closed, link closed. A SIGKILL or a power cut skips all of that, and
then the board's 200 ms watchdog stops the car on its own.
"""

from __future__ import annotations

import contextlib
import json
import logging
import secrets
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from carrt import __version__, rig_table
from carrt import config as car_config
from carrt.disk_space import check_room
from carrt.errors import UserError
from carrt.progress import recording_bar
from carrt.user_errors import USER_ERRORS
from firmware_bridge.link import BoardLink, LinkError

if TYPE_CHECKING:
    from carrt.loop_summary import LoopSummary

LOG = logging.getLogger(__name__)

# What a drive raises for something the user can fix (the CLI's one line and exit 2; a worker
# of carrt-sim-data writes the same line into the placement's log)
DRIVE_ERRORS = USER_ERRORS


@dataclass(frozen=True)
class DriveConfig:
    """One `carrt teleop` or `carrt drive` as data: made from the command line in one place
    (carrt/session_cmd.py), or by code (`carrt eval`, `carrt-sim-data`, the training loop),
    which never builds an argv. Frozen and picklable: a worker process gets one as its job.
    The fields are the flags of the same names (`sets`: the --set items)."""

    model: str | None = None  # the policy, .onnx or `demo`; None: teleop (a person or the expert)
    rig: str = "car"  # a row of carrt/rig_table.py (the command line's --rig, --sim, --board)
    config: str | None = None  # the car TOML; None: built-in defaults
    sets: tuple[str, ...] = ()  # SECTION.KEY=VALUE overrides of the car config
    port: str | None = None  # overrides serial.port
    camera: str | None = None  # overrides camera.source
    record: bool = False
    out: str | None = None  # episode directory, overrides episodes.dir
    duration: float | None = None  # s; None: until stopped
    seed: int = 0  # noise injection; on the simulator also the camera's phase and random starts
    summary_json: str | None = None
    view: str | None = None  # [HOST:]PORT of the live view
    # the simulator's (rows of carrt/rig_table.py that say simulator)
    layout: str = "easy"
    track_seed: int = 0
    realtime: bool = False  # forced by a person driving, a live view, or an emulated board
    episodes: int | None = None
    laps: int | None = None
    plot: str | None = None
    random_start: bool = False
    pad: bool = False  # a joystick instead of the keyboard window
    expert: bool = False  # teleop --expert auto: the scripted expert drives
    autopilot: bool = False  # the policy drives and the simulator's pilot re-arms
    expert_intervene: bool = False
    expert_noise: float = 0.0
    expert_noise_tau: float = 0.0  # s the expert's error lasts

    @property
    def command(self) -> str:
        return "teleop" if self.model is None else "drive"


@dataclass
class DriveResult:
    """What `run_session` returns: the loop's summary (laps, collisions, timings), the rig's
    own results (the simulator's: `carrt.sim.rig.SimRun`, metrics and trajectory; None on the
    car) and the signal that ended the run, if one did."""

    summary: LoopSummary
    rig: Any = None
    stopped_by: int | None = None

    @property
    def exit_code(self) -> int:
        """The command's: 0, or 128 + the signal that stopped it (130 for Ctrl-C)."""
        return 128 + self.stopped_by if self.stopped_by else 0


# The simulated car has no gearbox to strip: let it use the whole throttle range unless the
# user says otherwise (a real car's config starts at half throttle).
SIM_DEFAULTS = ("pwm.max_forward=1.0", "pwm.max_reverse=1.0")


def load_config(cfg: DriveConfig) -> car_config.CarConfig:
    """The car config the drive runs with: the TOML, the simulator's throttle range, the
    --set items, then the flags that override a key."""
    simulated = rig_table.lookup(cfg.rig).simulator
    overrides = [*(SIM_DEFAULTS if simulated else ()), *cfg.sets]
    for value, key in ((cfg.port, "serial.port"), (cfg.camera, "camera.source"),
                       (cfg.out, "episodes.dir")):  # fmt: skip
        if value is not None:
            overrides.append(f'{key}="{value}"')
    return car_config.load(cfg.config, overrides)


def _quiet(_line: str) -> None:
    """Where a session's lines go when its caller wants none (`carrt eval`, code)."""


def run_session(
    cfg: DriveConfig,
    *,
    log: logging.Logger | None = None,
    out: TextIO | None = None,
    progress: TextIO | None = None,
) -> DriveResult:
    """Drive once, as `cfg` says, and leave the car stopped; return what the run did.

    Nothing is printed unless asked: `log` takes the start-up and mode lines (the command line
    gives carrt.session's logger, so -v and -q apply), `out` the end-of-run report (the loop's
    summary, the simulator's metrics and saved files), `progress` the recording bar (shown
    where it is a terminal). Warnings still go through the `carrt` loggers. Raises one of
    DRIVE_ERRORS for what the user can fix."""
    config = load_config(cfg)
    say = log.info if log is not None else _quiet
    # Imported here: OpenCV, onnxruntime and pygame cost a second of start-up on a Jetson,
    # which `carrt check` and `carrt episodes` should not pay.
    from carrt.episodes.writer import EpisodeWriter
    from carrt.loop import ControlLoop, LoopParts
    from carrt.noise import NoiseInjector
    from carrt.policy import OnnxPolicy

    for flag, value in (("episodes", cfg.episodes), ("laps", cfg.laps)):
        if value is not None and value < 1:
            raise UserError(f"--{flag}: expected at least 1, got {value}")
    policy = None
    if cfg.model is not None:
        policy = OnnxPolicy(
            cfg.model,
            providers=tuple(config.loop.providers),
            intra_op_threads=config.loop.intra_op_threads,
            control_period_s=1.0 / config.loop.rate_hz,
        )
        warm = policy.warm_up()
        say(f"model {policy.path.name}: {policy.provider}, warm-up {warm[-1] * 1e3:.1f} ms")

    with contextlib.ExitStack() as stack:
        view = None
        if cfg.view is not None:
            from carrt.view.server import ViewServer

            view = ViewServer(cfg.view)  # binds now: a port in use ends here, car untouched
            stack.callback(view.close)
        rig = rig_table.open_rig(stack, cfg, config, driving=policy is not None)
        link = rig.link
        ack = link.keep_config(car_config.board_config(config))  # and after every reboot
        if ack.result != 0:
            raise UserError(
                f"board refused the PWM config from the car config (result {ack.result}): "
                "is it still armed by another process?"
            )

        sink = None
        if cfg.record:  # before the car moves: a disk without room refuses here
            room = check_room(config.episodes.dir, config.loop.rate_hz,
                              config.episodes.min_free_minutes)  # fmt: skip
            say(room)
            sink = EpisodeWriter(
                config.episodes.dir,
                queue_steps=config.episodes.queue_steps,
                sync_every_s=config.episodes.sync_every_s,
                # faster than real time a dropped step is lost data for nothing: wait instead
                wait_when_full=rig.simulated_time,
            )
            stack.callback(sink.close)
        parts = LoopParts(
            clock=rig.clock,
            camera=rig.camera,
            link=link,
            joystick=rig.joystick,
            policy=policy,
            sink=sink,
            noise=(
                NoiseInjector(config.noise, seed=cfg.seed)
                if policy is None or config.noise.during_auto
                else None
            ),
            collisions=rig.collisions,
        )
        metadata = _episode_metadata(config, policy, link, cfg.command)
        if rig_table.lookup(cfg.rig).simulator:
            metadata["sim"] = {"layout": cfg.layout, "track_seed": cfg.track_seed}
        loop = ControlLoop(
            parts,
            config,
            allow_auto=policy is not None,
            record=cfg.record,
            episode_metadata=metadata,
            max_steps=None if cfg.duration is None else round(cfg.duration * config.loop.rate_hz),
            # the scripted expert arms and disarms once per episode: its mode changes are
            # detail (-v), not news, or a 20-episode recording prints 40 of them
            log=_quiet if log is None else log.debug if cfg.expert else log.info,
        )
        for follower in rig.follows_mode:  # the sim's pilot and trajectory tracker
            follower.mode_source = lambda: loop.arbiter.mode
        for watcher in rig.watches_loop:  # the simulator's keyboard window
            watcher.status_source = lambda: loop.live
        if view is not None:
            from carrt.view.live import live_view

            live_view(view, loop, config, cfg.command)
        rig.joystick.start(on_estop=lambda: loop.estop("joystick"))
        stack.callback(rig.joystick.stop)
        stopped_by = _stop_on_signals(loop, stack)
        say(f"carrt {cfg.command}: {rig.describe}")
        with recording_bar(loop, enabled=cfg.record and progress is not None, stream=progress):
            summary = loop.run()
    if out is not None:
        print(summary.render(), file=out)
    result = DriveResult(summary, stopped_by=stopped_by[0] if stopped_by else None)
    try:  # the simulator's run files and the summary: a full disk here is one line too
        if rig.finish is not None:
            result.rig = rig.finish(summary, out)
        if cfg.summary_json:
            Path(cfg.summary_json).write_text(json.dumps(summary.to_dict(), indent=2) + "\n")
    except OSError as exc:
        if summary.write_error is None:
            raise UserError(
                f"could not save the run's files: {exc.strerror} ({exc.filename})"
            ) from None
    if link.error is not None:
        raise link.error
    if summary.write_error is not None:
        raise UserError(
            f"recording failed: {summary.write_error}; the episodes written before it are whole "
            "(carrt episodes show --verify)"
        )
    # Ctrl-C ends a drive cleanly (summary, episodes closed, car stopped): result.stopped_by
    return result


def _episode_metadata(config, policy, link: BoardLink, mode: str) -> dict[str, Any]:
    from carrt.faults import board_metadata

    board = link.board
    return {
        "carrt_version": __version__,
        "session": mode,
        # One recording session is one placement of the obstacles on a real car: training
        # holds out whole sessions (training.data.placement_key), so each run gets its own id.
        "session_id": f"{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(3)}",
        "car_config": config.to_dict(),
        "rate_hz": config.loop.rate_hz,
        "camera_source": config.camera.source,
        "model": None
        if policy is None
        else {
            "sha256": policy.sha256,
            "metadata": dict(policy.metadata),
            "provider": policy.provider,
        },
        "board": board_metadata(board),  # the loop names each episode's own boot
    }


def _stop_on_signals(loop: Any, stack: contextlib.ExitStack) -> list[int]:
    """SIGINT/SIGTERM end the run through the normal shutdown (only from the main thread);
    the previous handlers come back when the run ends, so a caller that runs several sessions
    in one process (carrt eval, the tests) is never left with a handler of a finished loop.
    Returns a list that will hold the signal that stopped the run, if one did."""
    caught: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        return caught

    def stop(signum: int, _frame: Any) -> None:
        caught.append(int(signum))
        loop.stop()

    for sig in (signal.SIGINT, signal.SIGTERM):
        stack.callback(signal.signal, sig, signal.getsignal(sig))
        signal.signal(sig, stop)
    return caught


__all__ = ["DRIVE_ERRORS", "DriveConfig", "DriveResult", "LinkError", "run_session"]
