"""The human's stand-in in the simulator, behind the Joystick interface.

It does what the person with the pad does in the paper's experiments: arms the car once it
stands still, drives it (with the scripted expert's sticks) or hands it to the policy (AUTO),
and after a collision resets the car onto the track, clears the e-stop and starts again. It
goes through the same arbitration and the same board as a person would: it only presses
buttons and moves sticks.

With intervene=True it is also the safety driver of the paper's interventions: while the policy
drives in AUTO and a collision is imminent (carrt.sim.lookahead), it moves the sticks to the
expert's command. The arbiter sees sticks moved in AUTO and hands over (MANUAL, the step
flagged `override`, the expert's sticks recorded as a* and executed); the pilot keeps driving
for at least INTERVENE_HOLD_S and until nothing is ahead, then centres the sticks and hands back
to AUTO. The policy thus gets labels in states it reached itself.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from carrt.interfaces import JoystickEvents, JoystickState, Mode

SETTLE_S = 0.5  # wait after a reset or a clear before the next press, as a person would
INTERVENE_HOLD_S = 1.0  # a safety driver who takes over keeps the sticks at least this long
START_LINE_M = 0.5  # a car this close to the line at arming starts a lap there (after a
# --laps episode the person sets the car down where it stopped, just past the line)


@dataclass
class PilotLog:
    episodes: int = 0
    collisions: int = 0
    laps: int = 0
    interventions: int = 0  # takeovers from the policy (intervene=True)


class SimPilot:
    def __init__(
        self,
        plant: Any,
        clock: Any,
        *,
        expert: Any = None,
        engage_auto: bool = False,
        episodes: int | None = None,
        laps_per_episode: int | None = None,
        random_start: bool = False,
        expert_noise: float = 0.0,
        expert_noise_tau: float = 0.0,
        seed: int = 0,
        intervene: bool = False,
    ) -> None:
        self.plant = plant
        self.clock = clock
        self.expert = expert
        self.engage_auto = engage_auto
        self.max_episodes = episodes
        self.laps_per_episode = laps_per_episode
        self.mode_source: Callable[[], Mode] = lambda: Mode.DISARMED
        self.log = PilotLog()
        self._mode = Mode.DISARMED
        self._since = clock.now()
        self._laps_at_arm = 0
        self._last_laps = 0
        self._pick_up = False
        self.random_start = random_start
        self.expert_noise = float(expert_noise)
        self.expert_noise_tau = float(expert_noise_tau)
        self._error = np.zeros(2)  # the person's error now (steering, throttle)
        self._error_at: float | None = None  # when it was last drawn
        self._rng = np.random.default_rng(seed)
        self._placed = False
        self.intervene = intervene and expert is not None
        self._taking_over = False
        self._hold_until = 0.0
        self._continuing = False  # the last episode ended in an e-stop: the trial goes on
        self._start_mark = False  # press the lap button once: a standing start at the line

    # Joystick interface ------------------------------------------------------------
    def start(self, on_estop: Callable[[], None]) -> None:
        del on_estop  # a simulated person never yanks the pad out

    def stop(self) -> None:
        pass

    def poll(self) -> JoystickState:
        now = self.clock.now()
        mode = self.mode_source()
        if mode != self._mode:
            self._on_mode_change(self._mode, mode, now)
        world = self.plant.world
        with self.plant.lock:
            state = world.car
            laps = world.laps
            new_lap = laps > self._last_laps  # the person presses the lap button at the line
            self._last_laps = laps
            sticks = (0.0, 0.0)
            if mode == Mode.MANUAL and self.expert is not None and not self.engage_auto:
                sticks = self._imperfect(self.expert.act(state))
            elif self.intervene:
                sticks = self._safety_driver(mode, now, state)
        events = self._decide(mode, now, laps)
        if new_lap or (self._start_mark and mode in (Mode.MANUAL, Mode.AUTO)):
            self._start_mark = False
            events = replace(events, lap=True)
        return JoystickState(
            connected=True,
            steering=float(sticks[0]),
            throttle=float(sticks[1]),
            neutral_since_connect=True,
            events=events,
        )

    # The person's decisions ----------------------------------------------------------
    def _imperfect(self, sticks: tuple[float, float]) -> tuple[float, float]:
        """The paper's robustness setting: a demonstrator whose every command carries Gaussian
        noise of σ expert_noise. Unlike the loop's noise injection (which the human corrects
        and which the episode keeps apart from a*), this noise IS the demonstration."""
        if self.expert_noise <= 0:
            return sticks
        noisy = np.clip(np.asarray(sticks) + self._person_error(), -1, 1)
        return float(noisy[0]), float(noisy[1])

    def _person_error(self) -> np.ndarray:
        """The error on this command: σ expert_noise on each stick. With expert_noise_tau = 0 a
        fresh draw every command (the literal reading of the paper; measured, that shows the
        policy recoveries and made imitation better, as DART's noise does). With τ > 0 the error
        lasts the way a person's does: an Ornstein-Uhlenbeck process of time constant τ, the
        same σ per command, correlated exp(−Δt/τ) with the last one. A lasting error is what
        makes a demonstration imperfect: at a state it put off the line the label still carries
        it, so imitation learns to under-correct. After a gap (between take-overs) it is fresh."""
        fresh = self._rng.normal(0.0, self.expert_noise, 2)
        now = self.clock.now()
        if self.expert_noise_tau <= 0 or self._error_at is None:
            self._error = fresh
        else:
            kept = math.exp(-max(0.0, now - self._error_at) / self.expert_noise_tau)
            self._error = kept * self._error + math.sqrt(1.0 - kept * kept) * fresh
        self._error_at = now
        return self._error

    def _safety_driver(self, mode: Mode, now: float, state) -> tuple[float, float]:
        """The expert's sticks while taking over from the policy, else centred sticks."""
        from carrt.sim.lookahead import collision_ahead

        if mode == Mode.AUTO and not self._taking_over:
            if not collision_ahead(self.plant.world):
                return 0.0, 0.0
            self._taking_over = True
            self._hold_until = now + INTERVENE_HOLD_S
            self.log.interventions += 1
        elif mode == Mode.MANUAL and self._taking_over:
            if now >= self._hold_until and not collision_ahead(self.plant.world):
                self._taking_over = False  # centred sticks now; _decide hands back to AUTO
                return 0.0, 0.0
        else:
            return 0.0, 0.0
        steering, throttle = self._imperfect(self.expert.act(state))  # the same person
        if steering == 0.0 and throttle == 0.0:
            throttle = -1e-3  # centred sticks would not register as a takeover
        return steering, throttle

    def _place_randomly(self) -> None:
        """Carry the resting car to a random clear place on the track, facing the racing
        direction: the expert then also shows how to start from rest anywhere, which the
        policy needs after every auto-reset (a start line only is a narrow demonstration)."""
        world = self.plant.world
        s = float(self._rng.uniform(0.0, world.track.length))
        self.plant.reset(world.clear_place_before(s))
        self._placed = True

    def _on_mode_change(self, old: Mode, new: Mode, now: float) -> None:
        self._mode, self._since = new, now
        if new != Mode.DISARMED:
            self._placed = False
        if new in (Mode.MANUAL, Mode.AUTO) and old == Mode.DISARMED:
            self._laps_at_arm = self._last_laps
            # carrt report's convention, as a person follows it: the lap button at every
            # crossing of the line, the start of a trial included (N marks make N-1 laps).
            # A trial that goes on after an e-stop and a reset has no new start.
            self._start_mark = not self._continuing and self._at_line()
            self._continuing = False
        if new == Mode.DISARMED and old in (Mode.MANUAL, Mode.AUTO):
            self._continuing = False  # a deliberate end: the next arm starts a new trial
        if new == Mode.DISARMED and self._pick_up:
            # The episode ended at the line: the person lifts the car off and sets it down at
            # rest. Braking to a stop inside the episode would teach a policy to stop there.
            self._pick_up = False
            with self.plant.lock:  # where it is now, not a physics step later
                self.plant.reset(self.plant.world.s)
        if new in (Mode.ESTOP, Mode.DISARMED):
            self._taking_over = False
        if new == Mode.ESTOP:
            self._continuing = True
            self.log.episodes += 1
            if self.plant.world.collided:
                self.log.collisions += 1
            self.plant.reset()  # carry the car back onto the track

    def _at_line(self) -> bool:
        """The car stands on the start line (within a body length), where laps are counted."""
        world = self.plant.world
        s, length = world.s, world.track.length
        return min(s, length - s) < START_LINE_M

    def _decide(self, mode: Mode, now: float, laps: int) -> JoystickEvents:
        if self.max_episodes is not None and self.log.episodes >= self.max_episodes:
            return JoystickEvents(quit=True)
        waited = now - self._since >= SETTLE_S
        if mode == Mode.DISARMED:
            still = abs(self.plant.world.car.v) < 0.01
            if self.random_start and not self._placed and still:
                self._place_randomly()
                self._since = now
                return JoystickEvents()
            return JoystickEvents(arm=waited and still)
        if mode == Mode.ESTOP:
            return JoystickEvents(clear=waited)
        driving_laps = laps - self._laps_at_arm
        if self.laps_per_episode is not None and driving_laps >= self.laps_per_episode:
            self._pick_up = True
            self.log.episodes += 1
            self.log.laps += driving_laps
            self._laps_at_arm = laps
            return JoystickEvents(arm=True)  # disarm: this episode is complete
        if mode == Mode.MANUAL and self.engage_auto and not self._taking_over:
            return JoystickEvents(toggle_auto=True)
        return JoystickEvents()
