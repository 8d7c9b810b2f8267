"""The 10 Hz control loop: camera → policy → arbitration → board, and the episode log.

Ticks start on a camera frame's arrival, phase-locked to a 10 Hz grid of deadlines on an
injectable clock (carrt/frame_lock.py), so the command leaves milliseconds after its frame and
one slow tick is an overrun that is counted, not a drift of every later tick; with the
simulated clock the same loop runs faster than real time. Each tick is split into timed sections
(capture, preprocess, inference, arbitration, actuation, logging) whose p50/p99 are reported
at exit with the achieved rate and the frame-to-command latency, in the spirit of openpilot's
rates and liveness as data.

Safety is not decided here: the arbiter (carrt.arbitration) decides what may be sent, and the
board has the last word. The loop only measures, asks and forwards, and it never blocks on
disk: steps go to the episode writer's bounded queue.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from carrt.arbitration import Arbiter, ArbiterInputs, Decision
from carrt.camera import preprocess
from carrt.config import CarConfig
from carrt.episode_rule import EpisodeRule
from carrt.faults import PartsWatch, board_metadata
from carrt.frame_lock import FrameLock
from carrt.interfaces import (
    Board,
    Camera,
    Clock,
    EpisodeSink,
    Joystick,
    LiveStatus,
    Mode,
    Policy,
)
from carrt.laps import LapCounter
from carrt.loop_summary import SECTIONS, LoopSummary, percentiles
from carrt.noise import NoiseInjector
from carrt.plan import PlanBuffer
from carrt.reasons import Why
from carrt.speed import SpeedEstimator
from carrt.tick import Tick
from firmware_bridge import messages as m

LOG = logging.getLogger(__name__)  # mode changes and refusals: what the person is told


class SectionTimer:
    """Wall time of each named section of one tick, lap by lap. perf_counter, not the loop's
    clock: on the simulated clock time stands still inside a tick, and the sections' cost in
    compute is what a user wants to see there too."""

    def __init__(self) -> None:
        self.times: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.times[name] = now - self._last
        self._last = now


@dataclass
class LoopParts:
    """Everything the loop talks to; real drivers and stand-ins are interchangeable."""

    clock: Clock
    camera: Camera
    link: Board
    joystick: Joystick
    policy: Policy | None = None
    sink: EpisodeSink | None = None
    noise: NoiseInjector | None = None
    # The simulator knows when the car hit something: True once per collision. On the real
    # car this stays None and the human's e-stop is the collision signal (as in the paper).
    collisions: Callable[[], bool] | None = None


class ControlLoop:
    """One driving session. `run()` returns when stopped, on quit, or after `max_steps`."""

    def __init__(
        self,
        parts: LoopParts,
        config: CarConfig,
        *,
        allow_auto: bool,
        record: bool,
        episode_metadata: dict[str, Any] | None = None,
        max_steps: int | None = None,
        log: Callable[[str], None] = LOG.info,
    ) -> None:
        self.parts = parts
        self.config = config
        self.period = 1.0 / config.loop.rate_hz
        self.frame_lock = FrameLock(self.period, 1.0 / config.camera.fps)
        self.record = record and parts.sink is not None
        self.episode_metadata = episode_metadata or {}
        self.max_steps = max_steps
        self.arbiter = Arbiter(
            allow_auto=allow_auto,
            camera=config.camera,
            encoder=config.encoder,
            deadzone=0.0,  # the pad driver already zeroes sticks inside its deadzone
            on_estop=parts.link.estop,
            # the keys to name in "not armed yet: press ..." (keyboard, pad preset)
            controls=getattr(parts.joystick, "controls", None),
        )
        self.speed = SpeedEstimator(config.encoder.metres_per_tick, config.encoder.speed_window_s)
        self.plans = PlanBuffer()
        self.stop_event = threading.Event()
        self.summary = LoopSummary()
        self._timings: dict[str, list[float]] = defaultdict(list)
        self._latency: list[float] = []
        self._lateness: list[float] = []
        self.episodes = EpisodeRule(record=self.record)
        self._step_index = 0
        self._last_frame_seq = -1
        self._last_message = ""
        self._collision_ended = False
        self._lap_counter = LapCounter()
        self.live = LiveStatus()  # replaced whole every tick: safe to read from other threads
        self._was_driving = False
        self.log = log
        self.watch = PartsWatch(parts, config)  # faults and reboots, said once each
        self._reboot_ended = False

    # ------------------------------------------------------------------ public
    def stop(self) -> None:
        self.stop_event.set()

    def estop(self, why: str) -> None:
        """For the joystick thread and signal handlers: latch e-stop, on the wire at once."""
        self.arbiter.estop(why)

    def run(self) -> LoopSummary:
        """Ticks on frame arrival, phase-locked to the camera on a 10 Hz grid
        (carrt/frame_lock.py); tick lateness is the time from that frame (or from the end of
        a window no frame came in) to the tick's start."""
        clock, camera, lock = self.parts.clock, self.parts.camera, self.frame_lock
        start = clock.now()
        deadline = start
        tick = 0
        try:
            while not self.stop_event.is_set():
                if self.max_steps is not None and tick >= self.max_steps:
                    break
                trigger = lock.wait(clock, camera, deadline)
                self._lateness.append(lock.lateness(trigger, deadline))
                if not self._tick(trigger.at):
                    break
                tick += 1
                deadline, late = lock.realign(lock.next_deadline(deadline, trigger), clock.now())
                self.summary.overruns += late
        finally:
            self._shutdown(clock.now() - start, tick)
        return self.summary

    # ------------------------------------------------------------------ one tick
    def _tick(self, tick_start: float) -> bool:
        """sense → infer → arbitrate → actuate → record, one Tick passed along; timed."""
        tick, sections = Tick(start=tick_start), SectionTimer()
        self._sense(tick, sections)  # capture, preprocess
        self._infer(tick)
        sections.lap("inference")
        self._arbitrate(tick)
        sections.lap("arbitration")
        self._actuate(tick)
        sections.lap("actuation")
        self._record(tick)
        sections.lap("logging")
        self._publish(tick, sections)
        return not tick.joystick.events.quit

    def _sense(self, tick: Tick, sections: SectionTimer) -> None:
        """The latest frame, sticks and telemetry, and whether the car hit something."""
        parts = self.parts
        tick.frame = parts.camera.latest()
        tick.joystick = parts.joystick.poll()
        # read after the sticks: a receiver that looks gone because its board rebooted is seen
        # with the reboot that explains it (the HELLO arrives before the new boot's telemetry)
        tick.rebooted = self.watch.board_reboot(parts.clock.now())
        tick.telemetry = parts.link.telemetry
        tick.collided = parts.collisions() if parts.collisions is not None else False
        if tick.collided:
            self.arbiter.estop(Why.COLLISION.text())
            self._collision_ended = True
            self.summary.collisions += 1
        sections.lap("capture")
        if tick.frame is not None:
            tick.image = preprocess(tick.frame.image, self.config.camera)
        if tick.telemetry is not None:
            tick.speed = self.speed.update(tick.telemetry.telemetry)
        sections.lap("preprocess")

    def _infer(self, tick: Tick) -> None:
        """A fresh plan for a new frame, unless the tick started too late for it to help."""
        policy, frame = self.parts.policy, tick.frame
        if policy is None:
            return
        if tick.image is None or frame.seq == self._last_frame_seq:
            tick.fallback_action = self.plans.fallback()
        elif self.parts.clock.now() - tick.start > 0.5 * self.period:
            self.summary.skipped_inferences += 1  # the last plan's next step instead
            tick.fallback_action = self.plans.fallback()
        else:
            tick.plan = policy.predict(tick.image, tick.speed)
            tick.plan_action = self.plans.fresh(tick.plan)
            self._last_frame_seq = frame.seq

    def _arbitrate(self, tick: Tick) -> None:
        """The arbiter decides what may be sent; noise injection perturbs what is executed."""
        parts, frame = self.parts, tick.frame
        tick.now = now = parts.clock.now()
        receiver_drives = bool(
            tick.telemetry and tick.telemetry.telemetry.flags & m.TelemetryFlags.RC_DRIVES
        )
        tick.decision = decision = self.arbiter.step(
            ArbiterInputs(
                now=now,
                joystick=tick.joystick,
                frame_age_s=None if frame is None else now - frame.captured_at,
                camera_lost=parts.camera.lost,
                telemetry_age_s=parts.link.telemetry_age_s(),
                board_state=parts.link.board_state,
                plan_action=tick.plan_action,
                fallback_action=tick.fallback_action,
                board_reason=tick.telemetry.telemetry.reason if tick.telemetry else 0,
                board_takeover=receiver_drives,
                camera_lost_reason=getattr(parts.camera, "lost_reason", None) or "",
                board_rebooted=tick.rebooted,
            )
        )
        self._report(decision, said=tick.rebooted)
        self.watch.faults_of(tick)
        self._count_laps(decision.mode, tick.joystick.events.lap)
        if decision.mode != Mode.ESTOP:
            self._collision_ended = False  # a later e-stop by hand is not this collision
        tick.executed = (decision.steering, decision.throttle)
        noise = parts.noise
        # while the board drives the receiver's pulses straight through, nothing the host adds
        # reaches the wheels: no noise is injected (or recorded as executed) then
        if (
            noise is not None
            and self.episodes.recording
            and noise.perturbs(decision.mode)
            and not receiver_drives
        ):
            ns, nt, tick.noisy = noise.sample(now)
            if tick.noisy:
                tick.executed = noise.apply(tick.executed, (ns, nt))

    def _actuate(self, tick: Tick) -> None:
        self._forward_requests(tick.decision)
        self.parts.link.set_auto(tick.decision.mode == Mode.AUTO)
        sent_at = self.parts.link.set_command(*tick.executed, send_now=True)
        tick.sent_at = math.nan if sent_at is None else sent_at
        if sent_at is not None and tick.frame is not None:
            self._latency.append(sent_at - tick.frame.captured_at)

    def _publish(self, tick: Tick, sections: SectionTimer) -> None:
        """Timings into the summary, and the tick's LiveStatus for whoever watches."""
        for name, seconds in sections.times.items():
            self._timings[name].append(seconds)
        decision = tick.decision
        self.live = tick.live_status(
            count=self.live.tick + 1,
            estop_reason=self.arbiter.estop_reason,
            plan=self.plans.plan,
            sections_s=sections.times,
            link=self.parts.link,
            recording=self.episodes.recording,
            summary=self.summary,
            alert=self._alert(),
            notices=self.watch.notices,
        )
        mode_name = decision.mode.name
        self.summary.modes_s[mode_name] = self.summary.modes_s.get(mode_name, 0.0) + self.period

    def _report(self, decision: Decision, said: str = "") -> None:
        """Tell the human what changed and why a press was refused (once per change); a mode
        whose reason is the line just `said` (a reboot's) is not said twice."""
        message = decision.mode.name
        if decision.reason:
            message += f" (neutral: {decision.reason})"
        if message != self._last_message:
            self._last_message = message
            if not (said and said in message):
                self.log(f"mode {message}")
        if decision.refused:
            self.log(f"refused: {decision.refused}")

    def _forward_requests(self, decision: Decision) -> None:
        link = self.parts.link
        if decision.clear_request:
            link.request_clear()
        if decision.disarm_request:
            link.disarm()
        if decision.arm_request:
            link.request_arm()

    # ------------------------------------------------------------------ recording
    def _record(self, tick: Tick) -> None:
        """The step into the episode writer's queue (never waits on disk); episodes begin and
        end by carrt/episode_rule.py."""
        sink, rule, decision = self.parts.sink, self.episodes, tick.decision
        if tick.joystick.events.toggle_record:
            rule.toggle_pause()
        board_armed = self.parts.link.board_state == m.State.ARMED
        if tick.rebooted and rule.recording:
            # the episode ends with the reboot in it; the next (after the re-arm) names the boot
            boot = board_metadata(self.watch.boot) or {}
            sink.event("board_reboot", {"text": tick.rebooted, **boot})
            self._reboot_ended = True
        if rule.should_begin(decision.mode, board_armed, tick.image is not None):
            meta = {**self.episode_metadata, "board": board_metadata(self.watch.boot)}
            sink.begin({**meta, "started_mode": decision.mode.name})
            rule.recording = True
            self.summary.episodes += 1
        if not rule.recording:
            return
        if tick.image is not None:
            self._step_index += 1
            if sink.write(tick.step(self._step_index - 1, time.time())):
                self.summary.recorded_steps += 1
            else:
                self.summary.dropped_steps += 1
                self._write_failed(getattr(sink, "error", None))
        if rule.should_end(decision.mode) or (self._reboot_ended and rule.recording):
            sink.end(self._end_reason(decision.mode))
            rule.recording = False
            self._collision_ended = False
        self._reboot_ended = False

    def _alert(self) -> str:
        error = self.summary.write_error
        return f"RECORDING FAILED: {error}" if error else ""

    def _write_failed(self, error: str | None) -> None:
        """The disk is full (or failing): said at once and loudly, whatever the log level, and
        the session ends through the normal shutdown (the car disarmed and stopped; the writer
        already closed the episode, readable up to its last whole step). Driving on would
        record nothing and nobody would know."""
        if error is None or self.summary.write_error is not None:
            return
        self.summary.write_error = error
        LOG.error(f"RECORDING FAILED: {error}; stopping the car and the session")
        self.stop_event.set()

    def _end_reason(self, mode: Mode) -> str:
        if self._reboot_ended:
            return "reboot"
        link = self.parts.link  # a silent board has stopped the car by its watchdog
        silent = link.telemetry_age_s() > self.config.encoder.max_age_s
        return LapCounter.end_reason(mode, self._collision_ended,
                                     link.board_state == m.State.FAILSAFE or silent)  # fmt: skip

    def _count_laps(self, mode: Mode, mark: bool) -> None:
        """The summary's laps and collisions, by the rule carrt report uses (carrt/laps.py)."""
        driving = mode in (Mode.MANUAL, Mode.AUTO)
        if self._was_driving and not driving:
            self._lap_counter.trial_end(self._end_reason(mode))
        self._was_driving = driving
        if mark:
            self._lap_counter.mark()
        self.summary.laps = self._lap_counter.laps

    # ------------------------------------------------------------------ exit
    def _shutdown(self, duration: float, ticks: int) -> None:
        link = self.parts.link
        link.disarm()
        link.set_command(0.0, 0.0, send_now=True)
        if self.episodes.recording:
            self.parts.sink.end("stopped")
            self.episodes.recording = False
        s = self.summary
        s.steps, s.duration_s = ticks, duration
        s.sections_ms = {name: percentiles(self._timings[name]) for name in SECTIONS}
        s.frame_to_command_ms = percentiles(self._latency)
        s.tick_lateness_ms = percentiles(self._lateness)
        s.max_tick_lateness_ms = max(self._lateness, default=math.nan) * 1e3
        s.interventions = self.arbiter.interventions
        s.estops = link.counters.estops_sent
