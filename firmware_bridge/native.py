"""The firmware's C core, compiled into the package and driven from Python through ctypes.

Tests and the simulator's virtual microcontroller run the very C code that is flashed onto the
board, not a Python re-implementation of it, so a safety rule can only be verified once. The
release library is compiled when the package is built (setup.py, as `firmware_bridge._fw_core`):
nothing is compiled or written at run time, so a car or laptop without a compiler runs the
virtual board too. A library built from other sources than the ones shipped beside it is refused
with one line saying how to rebuild. Only the sanitizer tests compile a build here, on demand,
into a per-user cache.
"""

from __future__ import annotations

import ctypes
import hashlib
import importlib.util
import os
import subprocess
import tempfile
import threading
from pathlib import Path

from firmware_bridge import messages as m
from firmware_bridge.core_sources import (
    CORE_SRC,
    FIRMWARE_DIR,
    LIBRARY_MODULE,
    SOURCES,
    WARNING_FLAGS,
    source_digest,
)

CC = "gcc"
SANITIZE_FLAGS = (
    "-fsanitize=address,undefined",
    "-fno-sanitize-recover=all",
    "-fno-omit-frame-pointer",
    "-O1",
    "-g",
)

TX_BUFFER = 8192  # the harness's serial TX capacity (FWH_TX_CAPACITY)
MAX_ENCODED_FRAME = 66  # FW_FRAME_MAX_ENCODED: 64 decoded bytes -> 65 COBS bytes + 0x00
RC_STEERING, RC_THROTTLE, RC_SWITCH = 0, 1, 2  # receiver channels (FW_RC_* in fw_core.h)
RC_TICKS_PER_US = 2  # Timer1's count: 0.5 us
RC_SETTLE_US = 500  # FW_RC_SETTLE_US: a pulse counts once its line has been quiet this long
REBUILD_HINT = "reinstall carrt (pip install .) or, in a checkout, run make"


class FirmwareBuildError(RuntimeError):
    """The C core library is missing, stale, or (sanitizer build) did not compile."""


class SanitizerRuntimeMissing(RuntimeError):
    """The sanitized build was asked for in a process without the ASan runtime preloaded."""


def release_library() -> Path:
    """Path of the library built with the package; FirmwareBuildError when there is none."""
    spec = importlib.util.find_spec(LIBRARY_MODULE)
    if spec is None or not spec.origin or not os.path.exists(spec.origin):
        raise FirmwareBuildError(
            f"the firmware core library ({LIBRARY_MODULE}) is not built: {REBUILD_HINT}"
        )
    return Path(spec.origin)


def _sanitizer_cache() -> Path:
    path = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "carrt"
    path.mkdir(parents=True, exist_ok=True)
    return path


_build_lock = threading.Lock()
_sanitized: Path | None = None


def build_sanitized_library() -> Path:
    """Compile the core with ASan+UBSan for the sanitizer tests (needs gcc; test time only).

    Cached under a hash of its sources and flags; the output is written under a temporary name
    and renamed into place, so several pytest processes may build at once.
    """
    global _sanitized
    with _build_lock:
        if _sanitized is not None and _sanitized.exists():
            return _sanitized
        flags = ("-fPIC", "-shared", *WARNING_FLAGS, *SANITIZE_FLAGS)
        digest = hashlib.sha256(f"{source_digest()} {CC} {' '.join(flags)}".encode())
        name = f"libcarrt_fw-{digest.hexdigest()[:16]}-san.so"
        out_dir = _sanitizer_cache()
        target = out_dir / name
        if not target.exists():
            fd, tmp_name = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=out_dir)
            os.close(fd)
            cmd = [CC, *flags, f"-I{CORE_SRC}", *map(str, SOURCES), "-o", tmp_name]
            try:
                result = subprocess.run(cmd, capture_output=True, text=True, check=False)
            except OSError as exc:
                os.unlink(tmp_name)
                raise FirmwareBuildError(f"cannot run {CC}: {exc}") from exc
            if result.returncode != 0:
                os.unlink(tmp_name)
                raise FirmwareBuildError(
                    f"building the sanitized firmware core failed ({' '.join(cmd)}):\n"
                    f"{result.stderr}"
                )
            os.chmod(tmp_name, 0o755)  # mkstemp made it private; the cache may be shared
            os.replace(tmp_name, target)
        _sanitized = target
        return target


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    c = ctypes
    u8p = c.POINTER(c.c_uint8)
    signatures = {
        "fwh_size": (c.c_size_t, []),
        "fwh_create": (None, [c.c_void_p]),
        "fwh_boot": (None, [c.c_void_p, c.c_uint32, c.c_uint8, c.c_uint32]),
        "fwh_rx": (None, [c.c_void_p, c.c_char_p, c.c_size_t, c.c_uint32]),
        "fwh_tick": (None, [c.c_void_p, c.c_uint32]),
        "fwh_tx_take": (c.c_size_t, [c.c_void_p, u8p, c.c_size_t]),
        "fwh_set_encoder": (None, [c.c_void_p, c.c_int32]),
        "fwh_pwm_us": (c.c_uint16, [c.c_void_p, c.c_uint8]),
        "fwh_state": (c.c_uint8, [c.c_void_p]),
        "fwh_reason": (c.c_uint8, [c.c_void_p]),
        "fwh_arm_refusal": (c.c_uint8, [c.c_void_p]),
        "fwh_counters": (None, [c.c_void_p, c.POINTER(c.c_uint16)]),
        "fwh_storage_size": (c.c_size_t, []),
        "fwh_storage_get": (None, [c.c_void_p, u8p]),
        "fwh_storage_set": (None, [c.c_void_p, u8p]),
        "fwh_protocol_hash": (c.c_uint32, []),
        "fwh_source_digest": (c.c_char_p, []),
        "fwh_payload_size": (c.c_int, [c.c_uint8]),
        "fwh_proto_roundtrip": (c.c_int, [c.c_uint8, c.c_char_p, c.c_size_t, u8p]),
        "fwh_encode_frame": (c.c_size_t, [c.c_uint8, c.c_uint16, c.c_char_p, c.c_size_t, u8p]),
        "fwh_crc16": (c.c_uint16, [c.c_char_p, c.c_size_t]),
        "fwh_crc32c": (c.c_uint32, [c.c_char_p, c.c_size_t]),
        "fwh_rc_size": (c.c_size_t, []),
        "fw_rc_init": (None, [c.c_void_p]),
        "fw_rc_edge": (c.c_uint8, [c.c_void_p, c.c_uint8, c.c_uint32, c.c_uint32]),
        "fw_rc_settle": (c.c_uint8, [c.c_void_p, c.c_uint32]),
        "fw_rc_restart": (None, [c.c_void_p]),
        "fw_rc_poll": (None, [c.c_void_p, c.c_uint32]),
        "fw_rc_valid": (c.c_uint8, [c.c_void_p]),
        "fw_rc_width_us": (c.c_uint16, [c.c_void_p]),
        "fwh_rc_edge": (None, [c.c_void_p, c.c_uint8, c.c_uint8, c.c_uint32, c.c_uint32]),
        "fwh_rc_settle": (None, [c.c_void_p, c.c_uint32, c.c_uint32]),
        "fwh_rc_settle_due": (c.c_uint8, [c.c_void_p, c.c_uint32]),
        "fwh_rc_overflow": (None, [c.c_void_p, c.c_uint8, c.c_uint32]),
        "fwh_rc_settle_us": (c.c_uint32, []),
        "fwh_rc_drives": (c.c_uint8, [c.c_void_p]),
        "fwh_rc_width_us": (c.c_uint16, [c.c_void_p, c.c_uint8]),
        "fwh_pwm_syncs": (c.c_uint32, [c.c_void_p]),
    }
    for name, (restype, argtypes) in signatures.items():
        fn = getattr(lib, name)
        fn.restype = restype
        fn.argtypes = argtypes
    return lib


_libs: dict[bool, ctypes.CDLL] = {}


def load_library(sanitize: bool = False) -> ctypes.CDLL:
    """The loaded harness. The sanitized build only loads into a process started with the
    ASan runtime preloaded (see tests/test_firmware_sanitizers.py)."""
    with _build_lock:
        lib = _libs.get(sanitize)
    if lib is None:
        if sanitize:
            # Without the runtime preloaded, ASan would abort the whole interpreter on dlopen.
            if not hasattr(ctypes.CDLL(None), "__asan_init"):
                raise SanitizerRuntimeMissing(
                    "the sanitized firmware needs the ASan runtime loaded first: run Python with "
                    "LD_PRELOAD=$(gcc -print-file-name=libasan.so) ASAN_OPTIONS=detect_leaks=0"
                )
            lib = _declare(ctypes.CDLL(str(build_sanitized_library())))
        else:
            path = release_library()
            lib = _declare(ctypes.CDLL(str(path)))
            built_from = lib.fwh_source_digest().decode()
            if built_from != source_digest():
                raise FirmwareBuildError(
                    f"the firmware core library {path.name} was built from other C sources "
                    f"({built_from}) than those in {FIRMWARE_DIR} ({source_digest()}): "
                    f"{REBUILD_HINT}"
                )
        with _build_lock:
            lib = _libs.setdefault(sanitize, lib)
    return lib


def _ms(now_ms: int) -> int:
    # The board's clock is a wrapping uint32 of milliseconds; callers may pass any int.
    return int(now_ms) & 0xFFFFFFFF


class FirmwareCore:
    """One simulated board: the C core with in-memory PWM, encoder, serial and storage.

    Nothing happens until ``boot``; the storage (the board's EEPROM) survives every later
    ``boot``, while RAM state and the encoder count do not.
    """

    def __init__(self, *, sanitize: bool = False) -> None:
        self._lib = load_library(sanitize)
        words = (self._lib.fwh_size() + 7) // 8  # uint64 cells: 8-byte alignment for the struct
        self._mem = (ctypes.c_uint64 * words)()
        self._h = ctypes.cast(self._mem, ctypes.c_void_p)
        self._lib.fwh_create(self._h)
        self._out = (ctypes.c_uint8 * TX_BUFFER)()

    def boot(self, boot_id: int, now_ms: int, reset_cause: int = m.ResetCause.POWER_ON) -> None:
        """Start (or restart) the board; its HELLO names reset_cause (a messages.ResetCause)."""
        self._lib.fwh_boot(self._h, int(boot_id) & 0xFFFFFFFF, int(reset_cause) & 0xFF, _ms(now_ms))

    def feed(self, data: bytes, now_ms: int) -> None:
        data = bytes(data)
        self._lib.fwh_rx(self._h, data, len(data), _ms(now_ms))

    def tick(self, now_ms: int) -> None:
        self._lib.fwh_tick(self._h, _ms(now_ms))

    def take_output(self) -> bytes:
        """Everything the board has written to its serial port since the last call."""
        n = self._lib.fwh_tx_take(self._h, self._out, TX_BUFFER)
        return bytes(self._out[:n])

    def set_encoder(self, ticks: int) -> None:
        # The board's counter is an int32 that wraps; so does this one.
        ticks = int(ticks) & 0xFFFFFFFF
        self._lib.fwh_set_encoder(self._h, ticks - (1 << 32) if ticks >= 1 << 31 else ticks)

    def rc_edge(self, channel: int, level: int, ticks: int, now_ms: int) -> None:
        """An edge on a receiver pin (RC_STEERING/RC_THROTTLE/RC_SWITCH), stamped with Timer1's
        0.5 us count (wrapping uint32) and the board's millisecond clock."""
        self._lib.fwh_rc_edge(
            self._h, int(channel), 1 if level else 0, int(ticks) & 0xFFFFFFFF, _ms(now_ms)
        )

    def rc_settle(self, ticks: int, now_ms: int) -> None:
        """The receiver's clock (Timer1's count, every edge before it handed over): a pulse
        counts once its line has been quiet RC_SETTLE_US, as a board's loop() pass finds."""
        self._lib.fwh_rc_settle(self._h, int(ticks) & 0xFFFFFFFF, _ms(now_ms))

    def rc_settle_due(self, ticks: int) -> bool:
        """Would rc_settle count a receiver pulse at this time?"""
        return bool(self._lib.fwh_rc_settle_due(self._h, int(ticks) & 0xFFFFFFFF))

    def rc_overflow(self, channels: int, now_ms: int) -> None:
        """Edges of these receiver channels (bit 1 << RC_*) were lost, as when the board's edge
        queue is full: they have no valid signal until a new run of good pulses."""
        self._lib.fwh_rc_overflow(self._h, int(channels) & 0xFF, _ms(now_ms))

    @property
    def rc_drives(self) -> bool:
        """The receiver's pulses drive the outputs (MANUAL from it, or a take-over)."""
        return bool(self._lib.fwh_rc_drives(self._h))

    def rc_width_us(self, channel: int) -> int:
        """The channel's last good pulse width; 0 while it has no valid signal."""
        return int(self._lib.fwh_rc_width_us(self._h, int(channel)))

    @property
    def pwm_syncs(self) -> int:
        """How often the core asked the outputs to start a frame now (a safety change)."""
        return int(self._lib.fwh_pwm_syncs(self._h))

    @property
    def steer_us(self) -> int:
        return int(self._lib.fwh_pwm_us(self._h, 0))

    @property
    def throttle_us(self) -> int:
        return int(self._lib.fwh_pwm_us(self._h, 1))

    @property
    def state(self) -> m.State:
        return m.State(self._lib.fwh_state(self._h))

    @property
    def reason(self) -> m.Reason:
        return m.Reason(self._lib.fwh_reason(self._h))

    @property
    def arm_refusal(self) -> m.ArmRefusal:
        return m.ArmRefusal(self._lib.fwh_arm_refusal(self._h))

    @property
    def counters(self) -> dict[str, int]:
        out = (ctypes.c_uint16 * 4)()
        self._lib.fwh_counters(self._h, out)
        return dict(zip(("bad_crc", "bad_length", "overruns", "tx_dropped"), out, strict=True))

    @property
    def storage(self) -> bytes:
        """The persistent config blob, e.g. to keep it in a file between simulator runs."""
        size = self._lib.fwh_storage_size()
        out = (ctypes.c_uint8 * size)()
        self._lib.fwh_storage_get(self._h, out)
        return bytes(out)

    @storage.setter
    def storage(self, blob: bytes) -> None:
        # A blob of another size (an older firmware's file) is cut or padded like erased
        # EEPROM (0xFF) rather than refused: the firmware itself must reject what it cannot
        # verify, exactly as it would on a board.
        size = self._lib.fwh_storage_size()
        data = bytes(blob[:size]).ljust(size, b"\xff")
        self._lib.fwh_storage_set(self._h, (ctypes.c_uint8 * size).from_buffer_copy(data))


def protocol_hash() -> int:
    """The hash compiled into the C core (CARRT_PROTOCOL_HASH)."""
    return int(load_library().fwh_protocol_hash())


def payload_size(type_id: int) -> int:
    """The C core's payload size for a type id (-1 when it does not know the type)."""
    return int(load_library().fwh_payload_size(int(type_id) & 0xFF))


def proto_roundtrip(type_id: int, payload: bytes) -> bytes | None:
    """Payload through the generated C unpack then pack: equal bytes mean both ends agree."""
    out = (ctypes.c_uint8 * m.MAX_FRAME_DECODED)()
    payload = bytes(payload)
    n = load_library().fwh_proto_roundtrip(int(type_id) & 0xFF, payload, len(payload), out)
    return None if n < 0 else bytes(out[:n])


def encode_frame(type_id: int, seq: int, payload: bytes) -> bytes:
    """Wire bytes (COBS + 0x00) from the C core's own encoder, for comparison with the codec."""
    out = (ctypes.c_uint8 * MAX_ENCODED_FRAME)()
    payload = bytes(payload)
    n = load_library().fwh_encode_frame(
        int(type_id) & 0xFF, int(seq) & 0xFFFF, payload, len(payload), out
    )
    if n == 0:
        raise ValueError(f"payload of {len(payload)} bytes does not fit in a frame")
    return bytes(out[:n])


def crc32c(data: bytes) -> int:
    """The C core's CRC-32C, the frames' CRC."""
    data = bytes(data)
    return int(load_library().fwh_crc32c(data, len(data)))


def crc16(data: bytes) -> int:
    """The C core's CRC-16/CCITT-FALSE (the stored config blob's)."""
    data = bytes(data)
    return int(load_library().fwh_crc16(data, len(data)))
