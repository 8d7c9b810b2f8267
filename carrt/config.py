"""The car's configuration: one TOML file per car, validated before anything moves.

Every field is declared once below with its type, default, allowed range and a comment; the
loader, the validator, `carrt config init` (which writes a commented default) and the CLI's
`--set section.key=value` overrides are all derived from those declarations. An unknown key,
a wrong type or an out-of-range value is an error that names the key: a typo in `max_forward`
must not silently leave the car at full throttle.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from carrt.errors import UserError
from firmware_bridge import timing

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10 (JetPack 6): the same parser, published as tomli before it joined stdlib
    import tomli as tomllib


def opt(default: Any, doc: str, *, lo: float | None = None, hi: float | None = None,
        choices: tuple | None = None) -> Any:  # fmt: skip
    """A config field: default, one-line doc, and its allowed range or choices."""
    meta = {"doc": doc, "lo": lo, "hi": hi, "choices": choices}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass
class SerialConfig:
    port: str = opt(
        "/dev/serial/by-id/CHANGE-ME", "board's serial port (a by-id path survives replugging)"
    )
    baud: int = opt(
        250000, "250000 on a 16 MHz AVR; native USB boards ignore it", lo=9600, hi=4_000_000
    )
    handshake_timeout_s: float = opt(
        3.0, "how long to wait for HELLO (boards reset on open)", lo=0.2, hi=30
    )


@dataclass
class PwmConfig:
    steer_left_us: int = opt(1000, "servo pulse at full left", lo=800, hi=2200)
    steer_center_us: int = opt(1500, "servo pulse straight ahead", lo=800, hi=2200)
    steer_right_us: int = opt(2000, "servo pulse at full right", lo=800, hi=2200)
    throttle_reverse_us: int = opt(1000, "ESC pulse at full reverse/brake", lo=800, hi=2200)
    throttle_neutral_us: int = opt(1500, "ESC pulse at neutral", lo=800, hi=2200)
    throttle_forward_us: int = opt(2000, "ESC pulse at full forward", lo=800, hi=2200)
    max_forward: float = opt(
        0.5, "largest forward throttle the board allows (start low)", lo=0.0, hi=1.0
    )
    max_reverse: float = opt(0.5, "largest reverse/brake throttle the board allows", lo=0.0, hi=1.0)
    slew_per_s: float = opt(
        2.0, "throttle rise limit per second on the board (falls are immediate)", lo=0.01, hi=100.0
    )


@dataclass
class CameraConfig:
    source: str = opt(
        "0", "V4L2 index ('0'), device path, GStreamer pipeline ending in appsink, or a video file"
    )
    width: int = opt(0, "capture width to request (0: the device default)", lo=0, hi=8192)
    height: int = opt(0, "capture height to request (0: the device default)", lo=0, hi=8192)
    fps: float = opt(30.0, "capture rate to request", lo=1.0, hi=240.0)
    crop_top: float = opt(
        0.0, "fraction of the image height cut from the top before resizing", lo=0.0, hi=0.9
    )
    crop_bottom: float = opt(0.0, "fraction cut from the bottom", lo=0.0, hi=0.9)
    crop_left: float = opt(0.0, "fraction cut from the left", lo=0.0, hi=0.9)
    crop_right: float = opt(0.0, "fraction cut from the right", lo=0.0, hi=0.9)
    max_age_s: float = opt(
        timing.CAMERA_MAX_AGE_S, "a frame older than this is refused: neutral command",
        lo=0.01, hi=1.0,
    )  # fmt: skip
    lost_after_s: float = opt(
        1.0, "no new frame for this long: camera lost, e-stop", lo=0.1, hi=10.0
    )
    loop_video: bool = opt(False, "restart a video file at its end instead of reporting it lost")


@dataclass
class EncoderConfig:
    metres_per_tick: float = opt(
        0.005, "distance per encoder tick (measure: push the car 1 m, count ticks)", lo=1e-6, hi=1.0
    )
    max_age_s: float = opt(
        timing.ENCODER_MAX_AGE_S, "telemetry older than this is refused: neutral command",
        lo=0.01, hi=1.0,
    )  # fmt: skip
    speed_window_s: float = opt(
        0.1, "speed is ticks over this window, from board timestamps", lo=0.02, hi=1.0
    )


@dataclass
class JoystickConfig:
    preset: str = opt("xbox", "button/axis layout", choices=("xbox", "ps4", "f710", "custom"))
    device_index: int = opt(0, "which pad when several are connected", lo=0, hi=15)
    steering_axis: int = opt(-1, "axis index for steering (-1: the preset's)", lo=-1, hi=31)
    throttle_axis: int = opt(-1, "axis index for throttle (-1: the preset's)", lo=-1, hi=31)
    invert_steering: bool = opt(False, "flip the steering axis")
    invert_throttle: bool = opt(True, "flip the throttle axis (sticks read -1 when pushed forward)")
    deadzone: float = opt(
        0.1, "stick values below this are zero; override needs more than this", lo=0.0, hi=0.5
    )
    max_throttle: float = opt(1.0, "scale of the human's throttle", lo=0.0, hi=1.0)
    estop_button: int = opt(-1, "button index for e-stop (-1: the preset's)", lo=-1, hi=31)
    arm_button: int = opt(-1, "button to arm/disarm (-1: the preset's)", lo=-1, hi=31)
    auto_button: int = opt(-1, "button to switch manual/auto (-1: the preset's)", lo=-1, hi=31)
    record_button: int = opt(-1, "button to start/stop recording (-1: the preset's)", lo=-1, hi=31)
    lap_button: int = opt(-1, "button to mark a lap (-1: the preset's)", lo=-1, hi=31)
    clear_button: int = opt(-1, "button to clear a latched e-stop (-1: the preset's)", lo=-1, hi=31)


@dataclass
class ReceiverConfig:
    """The car's own RC receiver wired to the board (D4 steering, D5 throttle, D6 switch), and
    which device holds the person's controls. `carrt calibrate --receiver` fills in the pulses."""

    controls: str = opt(
        "pad", "the person's controls: the game pad, the RC receiver, or both (a receiver stick "
        "then takes over on the board)", choices=("pad", "receiver", "both"),
    )  # fmt: skip
    steer_left_us: int = opt(1000, "receiver steering pulse at full left", lo=800, hi=2200)
    steer_center_us: int = opt(
        1500, "receiver steering pulse with the stick centred", lo=800, hi=2200
    )
    steer_right_us: int = opt(2000, "receiver steering pulse at full right", lo=800, hi=2200)
    throttle_reverse_us: int = opt(1000, "receiver throttle pulse at full brake", lo=800, hi=2200)
    throttle_neutral_us: int = opt(1500, "receiver throttle pulse at neutral", lo=800, hi=2200)
    throttle_forward_us: int = opt(
        2000, "receiver throttle pulse at full throttle", lo=800, hi=2200
    )
    deadzone_us: int = opt(
        60, "a stick further than this from its centre has moved (and takes over in AUTO)",
        lo=10, hi=500,
    )  # fmt: skip
    estop_us: int = opt(
        1700, "the switch channel at or above this pulse is its e-stop position", lo=800, hi=2200
    )
    gesture_s: float = opt(
        1.0, "arm: steering held full right this long, then let go", lo=0.3, hi=5.0
    )
    release_s: float = opt(
        0.5, "drive: both sticks let go this long after a take-over gives the wheels back to "
        "the policy", lo=0.2, hi=5.0,
    )  # fmt: skip


@dataclass
class NoiseConfig:
    fraction: float = opt(
        0.5, "share of recording time with noise injected (the paper: half)", lo=0.0, hi=1.0
    )
    amplitude: float = opt(
        0.3, "noise is uniform in [-amplitude, amplitude] (the paper: 0.3)", lo=0.0, hi=1.0
    )
    hold_min_s: float = opt(0.3, "each noise value is held at least this long", lo=0.1, hi=10.0)
    hold_max_s: float = opt(1.0, "and at most this long", lo=0.1, hi=10.0)
    period_s: float = opt(
        10.0, "noisy and clean stretches alternate within periods of this length", lo=1.0, hi=600.0
    )
    during_auto: bool = opt(
        False,
        "also perturb the policy's commands in AUTO while recording (world-model exploration "
        "data: varied actions near obstacles); the person keeps the override",
    )


@dataclass
class LoopConfig:
    rate_hz: float = opt(
        timing.LOOP_RATE_HZ,
        "control rate (the paper: 10 Hz); at least 5: the board fails safe when the decision "
        "has not changed for 300 ms",
        lo=5.0,
        hi=100.0,
    )
    providers: list = opt(
        ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"],
        "onnxruntime providers in order of preference (those not available are skipped)",
    )
    intra_op_threads: int = opt(0, "onnxruntime threads (0: its default)", lo=0, hi=64)


@dataclass
class EpisodesConfig:
    dir: str = opt("episodes", "where recorded episodes go")
    queue_steps: int = opt(32, "steps the writer may fall behind before it drops", lo=2, hi=10000)
    sync_every_s: float = opt(
        1.0, "fsync period: a power cut loses at most this much", lo=0.1, hi=10.0
    )
    min_free_minutes: float = opt(
        1.0, "recording refuses to start with room for fewer minutes than this", lo=0.1, hi=600.0
    )


@dataclass
class CarConfig:
    serial: SerialConfig = field(default_factory=SerialConfig)
    pwm: PwmConfig = field(default_factory=PwmConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    joystick: JoystickConfig = field(default_factory=JoystickConfig)
    receiver: ReceiverConfig = field(default_factory=ReceiverConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    episodes: EpisodesConfig = field(default_factory=EpisodesConfig)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return dataclasses.asdict(self)


SECTIONS = {f.name: f.type for f in dataclasses.fields(CarConfig)}
_SECTION_CLASSES = {f.name: f.default_factory for f in dataclasses.fields(CarConfig)}


def _check_value(key: str, spec: dataclasses.Field, value: Any) -> Any:
    default = spec.default if spec.default is not dataclasses.MISSING else spec.default_factory()
    kind = type(default)
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if (kind is bool and not isinstance(value, bool)) or not isinstance(value, kind):
        raise UserError(f"config {key}: expected {kind.__name__}, got {value!r}")
    if kind is int and isinstance(value, bool):
        raise UserError(f"config {key}: expected int, got {value!r}")
    if kind is float and not math.isfinite(value):
        # NaN compares False with every bound, so a range check alone would let it through
        # (a NaN max_age_s silently switched the stale-frame gate off).
        raise UserError(f"config {key}: expected a finite number, got {value!r}")
    meta = spec.metadata
    if meta.get("choices") and value not in meta["choices"]:
        raise UserError(f"config {key}: {value!r} is not one of {', '.join(meta['choices'])}")
    if meta.get("lo") is not None and value < meta["lo"]:
        raise UserError(f"config {key}: {value} is below the minimum {meta['lo']}")
    if meta.get("hi") is not None and value > meta["hi"]:
        raise UserError(f"config {key}: {value} is above the maximum {meta['hi']}")
    return value


def from_dict(data: dict[str, Any]) -> CarConfig:
    """Build and validate a config; raise UserError naming the first bad key."""
    config = CarConfig()
    for section, values in data.items():
        if section not in _SECTION_CLASSES:
            raise UserError(
                f"config: unknown section [{section}]{_did_you_mean(section, SECTIONS)} "
                f"(known: {', '.join(SECTIONS)})"
            )
        if not isinstance(values, dict):
            raise UserError(f"config {section}: expected a [{section}] table")
        target = getattr(config, section)
        specs = {f.name: f for f in dataclasses.fields(target)}
        for key, value in values.items():
            if key not in specs:
                raise UserError(f"config {section}.{key}: unknown key{_did_you_mean(key, specs)}")
            setattr(target, key, _check_value(f"{section}.{key}", specs[key], value))
    _check_consistency(config)
    return config


def _check_consistency(config: CarConfig) -> None:
    pwm = config.pwm
    lo, hi = sorted((pwm.steer_left_us, pwm.steer_right_us))
    if pwm.steer_left_us == pwm.steer_right_us or not lo <= pwm.steer_center_us <= hi:
        raise UserError(
            "config pwm.steer_center_us: must lie between steer_left_us and steer_right_us"
        )
    lo, hi = sorted((pwm.throttle_reverse_us, pwm.throttle_forward_us))
    if (
        pwm.throttle_forward_us == pwm.throttle_neutral_us
        or not lo <= pwm.throttle_neutral_us <= hi
    ):
        raise UserError("config pwm.throttle_neutral_us: must lie between reverse and forward")
    rc = config.receiver
    for name, (low, mid, high) in {
        "steer_center_us": (rc.steer_left_us, rc.steer_center_us, rc.steer_right_us),
        "throttle_neutral_us": (rc.throttle_reverse_us, rc.throttle_neutral_us,
                                rc.throttle_forward_us),
    }.items():  # fmt: skip
        lo, hi = sorted((low, high))
        if not lo + rc.deadzone_us < mid < hi - rc.deadzone_us:
            raise UserError(
                f"config receiver.{name}: must lie between its endpoints, a deadzone from each"
            )
    if config.noise.hold_min_s > config.noise.hold_max_s:
        raise UserError("config noise.hold_min_s: must not exceed noise.hold_max_s")
    if config.camera.crop_top + config.camera.crop_bottom >= 0.95:
        raise UserError("config camera.crop_top + crop_bottom: leaves no image")
    if config.camera.crop_left + config.camera.crop_right >= 0.95:
        raise UserError("config camera.crop_left + crop_right: leaves no image")


def load(path: str | Path | None, overrides: list[str] | None = None) -> CarConfig:
    """Read a TOML file (or defaults when path is None), apply `section.key=value` overrides."""
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        if path.is_dir():
            raise UserError(f"config file {path} is a directory, expected a .toml file")
        if not path.is_file():
            raise UserError(f"config file {path} does not exist (create one: carrt config init)")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise UserError(f"config file {path}: not valid TOML: {exc}") from exc
    for item in overrides or []:
        key, sep, raw = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot or not name:
            raise UserError(f"--set {item!r}: expected section.key=value")
        data.setdefault(section, {})
        if not isinstance(data[section], dict):
            raise UserError(f"config {section}: expected a [{section}] table")
        data[section][name] = _parse_override(raw.strip())
    return from_dict(data)


def _did_you_mean(word: str, known: Any) -> str:
    close = difflib.get_close_matches(word, list(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


def _parse_override(raw: str) -> Any:
    """A TOML value if it parses as one (1, 0.5, true, "x", [..]), else the bare string."""
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        return raw


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def render(config: CarConfig | None = None) -> str:
    """The config as commented TOML (what `carrt config init` writes)."""
    config = config or CarConfig()
    lines = [
        "# carrt car configuration. Every key is optional; unknown keys are errors.",
        "# Reference: docs/car.md, Configuration. Override one key on the command line with",
        "#   --set section.key=value",
        "",
    ]
    for section in SECTIONS:
        lines.append(f"[{section}]")
        obj = getattr(config, section)
        for spec in dataclasses.fields(obj):
            meta = spec.metadata
            bounds = ""
            if meta.get("choices"):
                bounds = f" ({' | '.join(meta['choices'])})"
            elif meta.get("lo") is not None:
                bounds = f" [{meta['lo']} .. {meta['hi']}]"
            lines.append(f"# {meta['doc']}{bounds}")
            lines.append(f"{spec.name} = {_toml_value(getattr(obj, spec.name))}")
        lines.append("")
    return "\n".join(lines)


def board_config(config: CarConfig, persist: bool = False) -> Any:
    """The board's CONFIG message for this car's PWM calibration and limits."""
    from firmware_bridge import messages as m

    pwm = config.pwm
    return m.Config(
        steer_left_us=pwm.steer_left_us,
        steer_center_us=pwm.steer_center_us,
        steer_right_us=pwm.steer_right_us,
        throttle_reverse_us=pwm.throttle_reverse_us,
        throttle_neutral_us=pwm.throttle_neutral_us,
        throttle_forward_us=pwm.throttle_forward_us,
        max_forward=round(pwm.max_forward * m.SCALE),
        max_reverse=round(pwm.max_reverse * m.SCALE),
        slew_per_s=round(pwm.slew_per_s * m.SCALE),
        persist=1 if persist else 0,
        controls=int(m.Controls[config.receiver.controls.upper()]),
        rc_steer_center_us=config.receiver.steer_center_us,
        rc_throttle_center_us=config.receiver.throttle_neutral_us,
        rc_deadzone_us=config.receiver.deadzone_us,
        rc_estop_us=config.receiver.estop_us,
    )
