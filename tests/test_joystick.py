"""The pygame joystick under SDL's dummy drivers, fed synthetic events from this thread.

No pad is attached: JOYDEVICEADDED cannot open a device, so the reader stays connected on the
events alone, and every event below goes through pygame's real queue into the reader thread.
"""

from __future__ import annotations

import os

os.environ["SDL_VIDEODRIVER"] = "dummy"
os.environ["SDL_AUDIODRIVER"] = "dummy"
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import threading
import time
from typing import ClassVar

import pygame
import pytest

from carrt.config import JoystickConfig
from carrt.errors import UserError
from carrt.interfaces import Joystick, JoystickEvents
from carrt.joystick import PRESETS, PygameJoystick, layout_for

INSTANCE = 0


class EstopProbe:
    """Records when and on which thread `on_estop` ran."""

    def __init__(self) -> None:
        self.calls: list[tuple[float, str]] = []
        self.called = threading.Event()

    def __call__(self) -> None:
        self.calls.append((time.perf_counter(), threading.current_thread().name))
        self.called.set()


def post(js: PygameJoystick, *events: tuple[int, dict]) -> None:
    """Post events and wait until the reader thread has taken all of them off the queue."""
    target = js.events_handled + len(events)
    for kind, attrs in events:
        pygame.event.post(pygame.event.Event(kind, attrs))
    deadline = time.monotonic() + 2.0
    while js.events_handled < target:
        assert time.monotonic() < deadline, "reader thread did not handle the events"
        time.sleep(0.0005)


def added(index: int = 0) -> tuple[int, dict]:
    return pygame.JOYDEVICEADDED, {"device_index": index}


def removed() -> tuple[int, dict]:
    return pygame.JOYDEVICEREMOVED, {"instance_id": INSTANCE}


def axis(number: int, value: float) -> tuple[int, dict]:
    return pygame.JOYAXISMOTION, {"instance_id": INSTANCE, "axis": number, "value": value}


def button(number: int) -> tuple[int, dict]:
    return pygame.JOYBUTTONDOWN, {"instance_id": INSTANCE, "button": number}


@pytest.fixture
def make():
    started: list[PygameJoystick] = []

    def factory(probe: EstopProbe | None = None, **config) -> PygameJoystick:
        js = PygameJoystick(JoystickConfig(**config))
        js.start(probe)
        started.append(js)
        return js

    yield factory
    for js in started:
        js.stop()


def neutral_connect(js: PygameJoystick) -> None:
    layout = js.layout
    post(js, added(), axis(layout.steering_axis, 0.0), axis(layout.throttle_axis, 0.0))
    assert js.poll().neutral_since_connect


# ----------------------------------------------------------------------------- layouts
def test_presets_and_overrides():
    assert layout_for(JoystickConfig(preset="xbox")) == PRESETS["xbox"]
    assert layout_for(JoystickConfig(preset="f710")) == PRESETS["xbox"]
    ps4 = layout_for(JoystickConfig(preset="ps4"))
    assert (ps4.estop, ps4.arm, ps4.clear) == (1, 9, 8)
    custom = layout_for(JoystickConfig(preset="xbox", throttle_axis=1, estop_button=0))
    assert (custom.throttle_axis, custom.estop, custom.arm) == (1, 0, 7)
    for layout in PRESETS.values():
        if layout.estop >= 0:
            buttons = [layout.estop, layout.arm, layout.auto, layout.record, layout.lap]
            assert len(set([*buttons, layout.clear])) == 6  # one role per button


def test_custom_needs_the_safety_roles():
    with pytest.raises(UserError, match="steering_axis"):
        layout_for(JoystickConfig(preset="custom"))
    full = JoystickConfig(
        preset="custom",
        steering_axis=2,
        throttle_axis=3,
        estop_button=0,
        arm_button=1,
        clear_button=2,
    )
    assert layout_for(full).auto == -1
    with pytest.raises(UserError, match="throttle_axis"):
        layout_for(JoystickConfig(steering_axis=4))


def test_implements_the_protocol(make):
    assert isinstance(make(), Joystick)


# ----------------------------------------------------------------------------- axes
@pytest.mark.parametrize("preset", ["xbox", "ps4", "f710"])
def test_axis_mapping_inversion_deadzone(make, preset):
    js = make(preset=preset, deadzone=0.1, max_throttle=0.5)
    layout = js.layout
    assert not js.poll().connected  # nothing connected at start: no pad until ADDED
    neutral_connect(js)
    post(js, axis(layout.steering_axis, 0.6), axis(layout.throttle_axis, -0.8))
    state = js.poll()
    assert state.connected
    assert state.steering == pytest.approx(0.6)
    assert state.throttle == pytest.approx(0.4)  # stick forward reads -1; scaled by 0.5
    post(js, axis(layout.steering_axis, -0.05), axis(layout.throttle_axis, 0.09))
    state = js.poll()
    assert (state.steering, state.throttle) == (0.0, 0.0)
    assert not state.sticks_moved
    post(js, axis(layout.steering_axis, -1.0), axis(layout.throttle_axis, 1.0))
    state = js.poll()
    assert (state.steering, state.throttle) == (pytest.approx(-1.0), pytest.approx(-0.5))
    post(js, axis(2, 1.0), axis(5, -1.0))  # triggers and other axes: ignored
    assert js.poll().steering == pytest.approx(-1.0)


def test_inversion_flags(make):
    js = make(invert_steering=True, invert_throttle=False)
    neutral_connect(js)
    post(js, axis(0, 0.5), axis(4, 0.7))
    state = js.poll()
    assert (state.steering, state.throttle) == (pytest.approx(-0.5), pytest.approx(0.7))


def test_events_from_another_device_index_are_not_a_connect(make):
    js = make(device_index=1)
    post(js, added(0))
    assert not js.poll().connected
    post(js, added(1))
    assert js.poll().connected


# ----------------------------------------------------------------------------- buttons
def test_each_press_reported_exactly_once(make):
    js = make()
    neutral_connect(js)
    layout = js.layout
    roles = {
        layout.arm: "arm",
        layout.auto: "toggle_auto",
        layout.record: "toggle_record",
        layout.lap: "lap",
        layout.clear: "clear",
    }
    for number, edge in roles.items():
        post(js, button(number))
        assert js.poll().events == JoystickEvents(**{edge: True})
        assert js.poll().events == JoystickEvents()
    post(js, button(layout.lap), button(layout.lap), (pygame.JOYBUTTONUP, {"button": 5}))
    assert js.poll().events == JoystickEvents(lap=True)
    assert js.poll().events == JoystickEvents()
    post(js, button(0), button(10))  # unmapped buttons: nothing
    assert js.poll().events == JoystickEvents()
    post(js, (pygame.QUIT, {}))
    assert js.poll().events == JoystickEvents(quit=True)


def test_estop_button_calls_back_from_the_reader_at_once_without_a_poll(make):
    probe = EstopProbe()
    js = make(probe)
    neutral_connect(js)
    latencies = []
    for _ in range(5):
        probe.called.clear()
        t0 = time.perf_counter()
        pygame.event.post(pygame.event.Event(*button(js.layout.estop)))
        assert probe.called.wait(1.0)
        latencies.append(probe.calls[-1][0] - t0)
    assert len(probe.calls) == 5
    assert {name for _, name in probe.calls} == {"joystick-reader"}
    assert max(latencies) < 0.05, latencies
    assert js.poll().events == JoystickEvents(estop=True)  # also an edge, once
    assert js.poll().events == JoystickEvents()


def test_estop_button_works_even_before_a_connect(make):
    probe = EstopProbe()
    js = make(probe)
    post(js, button(js.layout.estop))
    assert len(probe.calls) == 1


def test_a_failing_callback_does_not_kill_the_reader(make):
    def broken() -> None:
        raise RuntimeError("link gone")

    js = make(broken)
    neutral_connect(js)
    post(js, button(js.layout.estop))
    post(js, axis(0, 0.5))
    assert js.poll().steering == pytest.approx(0.5)


# ----------------------------------------------------------------------------- (re)connects
def test_removal_estops_at_once_and_disconnects(make):
    probe = EstopProbe()
    js = make(probe)
    neutral_connect(js)
    post(js, axis(0, 0.7))
    t0 = time.perf_counter()
    pygame.event.post(pygame.event.Event(*removed()))
    assert probe.called.wait(1.0)
    assert probe.calls[0][0] - t0 < 0.05 and probe.calls[0][1] == "joystick-reader"
    time.sleep(0.01)
    state = js.poll()
    assert not state.connected and not state.neutral_since_connect
    assert (state.steering, state.throttle) == (0.0, 0.0)
    post(js, removed())  # a second removal of a pad already gone: nothing more
    assert len(probe.calls) == 1


def test_neutral_required_after_every_connect(make):
    js = make()
    post(js, added())
    state = js.poll()
    assert state.connected and not state.neutral_since_connect
    post(js, axis(0, 0.02))
    assert not js.poll().neutral_since_connect  # one mapped axis seen, the other not yet
    post(js, axis(4, -0.05))
    assert js.poll().neutral_since_connect
    post(js, axis(4, -0.9))
    assert js.poll().neutral_since_connect  # moving later does not undo it: arming checks sticks
    post(js, removed(), added())
    assert not js.poll().neutral_since_connect  # every reconnect asks again


def test_stuck_at_full_scale_after_reconnect(make):
    js = make()
    neutral_connect(js)
    post(js, removed(), added(), axis(4, -1.0), axis(0, 0.0))  # wireless pad lies: full forward
    for _ in range(3):
        post(js, axis(4, -1.0), axis(0, 0.0))  # however long it keeps saying so
        state = js.poll()
        assert state.connected and not state.neutral_since_connect
        assert state.throttle == pytest.approx(1.0)
    post(js, axis(4, -0.5))
    assert not js.poll().neutral_since_connect
    post(js, axis(4, 0.0))  # moved back to neutral: now it may arm
    state = js.poll()
    assert state.neutral_since_connect and not state.sticks_moved


def test_stop_is_clean_and_restartable():
    for _ in range(2):
        js = PygameJoystick(JoystickConfig())
        js.start(None)
        post(js, added(), axis(0, 0.5))
        assert js.poll().steering == pytest.approx(0.5)
        js.stop()
        assert not pygame.display.get_init() and not pygame.joystick.get_init()
    js.stop()  # twice is harmless


# ----------------------------------------------------------------------------- an opened pad
class FakeDevice:
    """Stands in for pygame.joystick.Joystick when SDL has a real pad: get_axis is the truth."""

    axes: ClassVar[dict[int, float]] = {0: 0.0, 4: 0.0}

    def __init__(self, index: int) -> None:
        self.index = index

    def init(self) -> None: ...

    def quit(self) -> None: ...

    def get_instance_id(self) -> int:
        return 42

    def get_name(self) -> str:
        return "Fake Pad"

    def get_numaxes(self) -> int:
        return 6

    def get_axis(self, number: int) -> float:
        return self.axes.get(number, 0.0)


def wait_for(predicate, timeout=1.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline
        time.sleep(0.002)


def test_opened_pad_stuck_axis_seen_by_reading_it(make, monkeypatch):
    monkeypatch.setattr(pygame.joystick, "Joystick", FakeDevice)
    monkeypatch.setattr(FakeDevice, "axes", {0: 0.0, 4: -1.0})  # stuck at full forward, no events
    probe = EstopProbe()
    js = make(probe)
    post(js, added())
    assert js.name == "Fake Pad"
    time.sleep(0.05)  # a dozen reader iterations: still not neutral, and the value shows
    state = js.poll()
    assert state.connected and not state.neutral_since_connect
    assert state.throttle == pytest.approx(1.0)
    FakeDevice.axes[4] = 0.0  # the human moves it back
    wait_for(lambda: js.poll().neutral_since_connect)
    # events of another pad (another instance id) are not ours; its removal is not an e-stop
    post(js, (pygame.JOYAXISMOTION, {"instance_id": 7, "axis": 0, "value": 0.9}))
    post(js, (pygame.JOYBUTTONDOWN, {"instance_id": 7, "button": js.layout.arm}))
    post(js, (pygame.JOYDEVICEREMOVED, {"instance_id": 7}))
    state = js.poll()
    assert state.connected and state.steering == 0.0 and state.events == JoystickEvents()
    assert probe.calls == []
    post(js, (pygame.JOYDEVICEREMOVED, {"instance_id": 42}))
    assert len(probe.calls) == 1 and not js.poll().connected


def test_opened_pad_without_the_mapped_axis_reports_a_problem(make, monkeypatch):
    monkeypatch.setattr(pygame.joystick, "Joystick", FakeDevice)
    monkeypatch.setattr(FakeDevice, "get_numaxes", lambda self: 2)
    js = make()
    post(js, added())
    assert "axis 4 does not exist" in js.problem
    time.sleep(0.02)
    assert not js.poll().neutral_since_connect  # it can never arm


# ----------------------------------------------------------------------------- with a receiver
def test_pad_and_receiver_together(make):
    """`receiver.controls = "both"`: the pad's buttons, the transmitter's sticks once moved, and
    connected only while both are (the receiver is read back from a real C core's TELEMETRY)."""
    from carrt.clock import SimClock
    from carrt.config import ReceiverConfig
    from carrt.receiver import PadAndReceiver, ReceiverControls
    from firmware_bridge import messages as m
    from firmware_bridge.direct import DirectBoardLink
    from firmware_bridge.drivetrain import WheelPlant

    clock = SimClock(step_s=0.002)
    link = DirectBoardLink(WheelPlant(), clock).open()
    link.send_config(m.Config(controls=int(m.Controls.BOTH)))
    pad = make()
    both = PadAndReceiver(pad, ReceiverControls(link, ReceiverConfig(controls="both"), clock.now))
    neutral_connect(pad)
    clock.advance(0.2)
    assert not both.poll().connected, "no receiver signal yet"
    link.set_receiver(1500, 1500, 1000)
    clock.advance(0.2)
    state = both.poll()
    assert state.connected and state.neutral_since_connect
    post(pad, axis(pad.layout.steering_axis, 0.5))
    assert both.poll().steering == pytest.approx(pad.poll().steering), "the pad's sticks"
    link.set_receiver(1280, 1500, 1000)  # the transmitter's stick moves: it wins
    clock.advance(0.1)
    assert both.poll().steering == pytest.approx(-(220 - 60) / 440)
    post(pad, button(pad.layout.arm))
    assert both.poll().events.arm, "the pad's buttons"
    post(pad, removed())
    assert not both.poll().connected, "the pad gone: disconnected, as for the pad alone"
