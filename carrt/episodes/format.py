"""The episode format on disk: one directory per episode, three append-only or atomic files.

```
<root>/<YYYYmmdd-HHMMSS>-<nnn>/
    meta.json     metadata; written atomically (tmp + fsync + rename) at begin, again at end
    frames.u8     N x 27648 bytes: frame i is the (96, 96, 3) uint8 RGB image at i * 27648
    steps.bin     N fixed-size records (STEP_DTYPE, little-endian); record i describes frame i
    synced.json   {"steps": n}: the first n steps are known durable (rewritten after each fsync)
```

Why this shape: a power cut can only tear the end of the two append-only files, and each
record carries a CRC-32 over itself and its frame, so the reader finds the last good step by
itself; `synced.json` tells it where checking can start, so opening a 94K-frame dataset does not
mean hashing 2.6 GB. Frames are one fixed-record file so training can memory-map them. The record
dtype is written into meta.json, so numpy alone can read any episode without this package.

A step record is committed when its CRC matches: the writer appends the frame first, then the
record, so a record never describes a frame that is not on disk.
"""

from __future__ import annotations

import errno
import json
import os
import re
import struct
import time
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from carrt.interfaces import STEP_FIELDS, Step, StepField
from carrt.model_contract import HORIZON, IMAGE_SHAPE

SCHEMA = "carrt.episode/1"
SCHEMA_MAJOR = SCHEMA.rsplit("/", 1)[1]

META = "meta.json"
FRAMES = "frames.u8"
STEPS = "steps.bin"
SYNCED = "synced.json"

FRAME_BYTES = int(np.prod(IMAGE_SHAPE))  # 27648
MAGIC = 0x31455243  # b"CRE1" little-endian: a zero-filled tail can never look like a record
COLLISION_WINDOW_S = 0.5  # the paper labels the 0.5 s before a collision (5 frames at 10 Hz)
WINDOW_TOLERANCE_S = 1e-6  # t_k - 0.5 s computed in floating point must not admit a 6th frame

END_CRASHED = "crashed"  # what the reader reports for an episode whose end was never written
END_DISK_FULL = "disk full"
END_WRITE_ERROR = "write error"
COLLISION_END_REASONS = ("collision", "estop")

# the on-disk columns of STEP_FIELDS, in record order; the flags are its one-byte bools
COLUMNS = tuple(f for f in STEP_FIELDS if f.disk)
FLAGS = tuple(f.name for f in COLUMNS if f.disk == "?")


def step_dtype(horizon: int = HORIZON) -> np.dtype:
    """The record layout: a magic number and the record's number, the Step's columns
    (carrt/interfaces.py STEP_FIELDS) in their order, padding, a CRC. Fields are naturally
    aligned and the record is a multiple of 8 bytes.

    `crc` must stay the last 4 bytes: it is CRC-32 over the record's other bytes, then the frame.
    """
    fields: list[tuple[Any, ...]] = [
        ("magic", "<u4"),
        ("seq", "<u4"),  # record number in this file: a record copied to the wrong place fails
    ]
    for column in COLUMNS:
        shape = tuple(horizon if d == "horizon" else d for d in column.shape)
        fields.append((column.name, column.disk, shape) if shape else (column.name, column.disk))
    size = np.dtype(fields).itemsize + 4
    pad = -size % 8
    if pad:
        fields.append(("_reserved", "u1", (pad,)))
    fields.append(("crc", "<u4"))
    return np.dtype(fields)


STEP_DTYPE = step_dtype(HORIZON)


def dtype_to_json(dtype: np.dtype) -> dict[str, Any]:
    """Names, formats and offsets: enough for `np.dtype(...)` to rebuild it byte for byte."""
    formats = []
    for name in dtype.names:
        sub = dtype.fields[name][0]
        formats.append((str(sub.shape) if sub.shape else "") + sub.base.str)
    return {
        "names": list(dtype.names),
        "formats": formats,
        "offsets": [dtype.fields[n][1] for n in dtype.names],
        "itemsize": dtype.itemsize,
    }


def dtype_from_json(spec: dict[str, Any]) -> np.dtype:
    """The inverse of dtype_to_json. Each sub-array's shape ("(10,)<f4") is parsed here rather
    than by numpy, which hands it to Python's parser, and CPython 3.11's parser is not safe to
    run from two threads at once (gh-106905: a spurious SystemError): the study's chains read
    episodes from threads side by side."""
    return np.dtype(
        {
            "names": spec["names"],
            "formats": [_field_format(f) for f in spec["formats"]],
            "offsets": spec["offsets"],
            "itemsize": spec["itemsize"],
        }
    )


_SUBARRAY = re.compile(r"^\((\d+(?:\s*,\s*\d+)*)\s*,?\)(.+)$")


def _field_format(text: str) -> np.dtype | tuple[np.dtype, tuple[int, ...]]:
    """ "<f4" or "(10,)<f4" (what dtype_to_json writes) as a dtype or (base, shape)."""
    match = _SUBARRAY.match(text)
    if match is None:
        return np.dtype(text)
    return np.dtype(match.group(2)), tuple(int(n) for n in match.group(1).split(","))


def format_metadata(dtype: np.dtype) -> dict[str, Any]:
    """The part of meta.json that says how to read the files with numpy alone."""
    horizon = dtype.fields["plan_mu"][0].shape[0]
    return {
        "frames": {"file": FRAMES, "dtype": "uint8", "shape": list(IMAGE_SHAPE)},
        "steps": {"file": STEPS, "dtype": dtype_to_json(dtype)},
        "horizon": horizon,
        "checksum": "zlib.crc32 over each record without its last 4 bytes, continued over its "
        "frame; stored in the record's last 4 bytes (crc)",
        "synced": SYNCED,
    }


def plan_rows(plan: np.ndarray | None, horizon: int) -> np.ndarray:
    """A plan as exactly `horizon` rows: NaN when absent, cut or NaN-padded if sized otherwise."""
    out = np.full((horizon, 2), np.nan, dtype=np.float32)
    if plan is not None:
        plan = np.asarray(plan, dtype=np.float32).reshape(-1, 2)
        rows = min(horizon, plan.shape[0])
        out[:rows] = plan[:rows]
    return out


# The columns before the plans (magic … executed_action) and after them (mode, flags), each
# packed by one struct call: that keeps the writer thread's hold on the GIL short, so the loop
# thread rarely waits. The plans, sized by the episode's horizon, are copied in between.
_STRUCT_CODE = {"<u4": "I", "<i8": "q", "<f8": "d", "<f4": "f", "u1": "B", "?": "?"}
_PLANS = tuple(f.name for f in COLUMNS if "horizon" in f.shape)
_FIRST_PLAN = COLUMNS.index(next(f for f in COLUMNS if f.name == _PLANS[0]))
_HEAD_COLUMNS = COLUMNS[:_FIRST_PLAN]
_TAIL_COLUMNS = COLUMNS[_FIRST_PLAN + len(_PLANS) :]


def _struct(columns: tuple[StepField, ...], prefix: str = "") -> struct.Struct:
    codes = (_STRUCT_CODE[f.disk] * int(np.prod(f.shape, dtype=int)) for f in columns)
    return struct.Struct("<" + prefix + "".join(codes))


_HEAD = _struct(_HEAD_COLUMNS, prefix="II")  # magic, seq, then the Step's
_TAIL = _struct(_TAIL_COLUMNS)
_HEAD_VALUES = [(f.name, bool(f.shape)) for f in _HEAD_COLUMNS]  # (name, is a pair)
assert STEP_DTYPE.fields[_PLANS[0]][1] == _HEAD.size, "step_dtype and _HEAD disagree"
assert all(COLUMNS[_FIRST_PLAN + i].name == name for i, name in enumerate(_PLANS))
_TAIL_LAST = STEP_DTYPE.fields[_TAIL_COLUMNS[-1].name]
assert STEP_DTYPE.fields[_TAIL_COLUMNS[0].name][1] + _TAIL.size == _TAIL_LAST[1] + 1


def pack_step(step: Step, image: bytes, seq: int, dtype: np.dtype = STEP_DTYPE) -> bytes:
    """One record, CRC included. `image` is the frame's 27648 bytes as they go to frames.u8."""
    fields = dtype.fields
    horizon = fields[_PLANS[0]][0].shape[0]
    raw = bytearray(dtype.itemsize)
    head: list[Any] = [MAGIC, seq]
    for name, pair in _HEAD_VALUES:
        if pair:
            head.extend(getattr(step, name))
        else:
            head.append(getattr(step, name))
    _HEAD.pack_into(raw, 0, *head)
    for name in _PLANS:
        offset = fields[name][1]
        raw[offset : offset + 8 * horizon] = plan_rows(getattr(step, name), horizon).tobytes()
    tail = (getattr(step, f.name) for f in _TAIL_COLUMNS)
    _TAIL.pack_into(raw, fields[_TAIL_COLUMNS[0].name][1], *tail)
    crc = zlib.crc32(image, zlib.crc32(memoryview(raw)[:-4]))
    raw[-4:] = crc.to_bytes(4, "little")
    return bytes(raw)


def record_crc(record: bytes | memoryview, frame: bytes | memoryview) -> int:
    return zlib.crc32(frame, zlib.crc32(record[:-4]))


def write_records(
    path: Path, records: np.ndarray, frames: np.ndarray, meta: dict[str, Any]
) -> None:
    """A whole episode written at once into the existing folder `path` (salvage, import): the
    records renumbered and their CRCs computed over each record and its frame, the files made
    durable, then synced.json and meta.json."""
    records = records.copy()
    records["seq"] = np.arange(len(records), dtype=records["seq"].dtype)
    raw = records.view(np.uint8).reshape(len(records), records.dtype.itemsize)
    frames = np.ascontiguousarray(frames, dtype=np.uint8).reshape(len(records), FRAME_BYTES)
    for i in range(len(records)):
        records["crc"][i] = record_crc(raw[i], frames[i])
    for name, array in ((STEPS, records), (FRAMES, frames)):
        with open(path / name, "wb") as f:
            array.tofile(f)
            f.flush()
            os.fsync(f.fileno())
    write_json_atomic(path / SYNCED, {"steps": len(records)})
    write_json_atomic(path / META, meta)


def fsync_dir(path: Path) -> None:
    """Make a create/rename inside `path` durable (a no-op where directories cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def new_episode_dir(root: Path, wall: float) -> Path:
    """`<YYYYmmdd-HHMMSS>-<nnn>`, unique even when a car without an RTC repeats a clock."""
    stem = time.strftime("%Y%m%d-%H%M%S", time.localtime(wall))
    for n in range(100_000):
        path = root / f"{stem}-{n:03d}"
        try:
            path.mkdir()
        except FileExistsError:
            continue
        fsync_dir(root)
        return path
    raise FileExistsError(errno.EEXIST, "no free episode name", str(root / stem))


def write_all(fd: int, data: bytes) -> None:
    """All of `data` to `fd`: os.write may write less than asked (a pipe, a signal, a full disk)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def datasync(fd: int) -> None:
    """The file's data on the disk (fdatasync where the OS has it: the size, not the times)."""
    (os.fdatasync if hasattr(os, "fdatasync") else os.fsync)(fd)


def write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    """Either the old file or the new one survives a power cut, never half of one."""
    tmp = path.with_name(f".{path.name}.tmp")
    text = json.dumps(data, indent=1, default=_json_default, allow_nan=True) + "\n"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        view = memoryview(text.encode())
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    fsync_dir(path.parent)


def _json_default(value: Any) -> Any:
    """Metadata comes from configs and models: numpy scalars, paths, dataclasses, enums."""
    import dataclasses
    import enum

    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    if isinstance(value, enum.Enum):
        return value.name
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (set, frozenset, tuple)):
        return list(value)
    return str(value)


def run_metadata(
    *,
    command: str,
    car_config: Any = None,
    model_sha256: str | None = None,
    model_metadata: dict[str, str] | None = None,
    model_path: str | None = None,
    horizon: int = HORIZON,
    **extra: Any,
) -> dict[str, Any]:
    """The metadata the loop passes to begin(): the keys `carrt episodes` and training read.

    `car_config` may be a CarConfig or its dict; `model` is None when a human drives.
    """
    import dataclasses

    if dataclasses.is_dataclass(car_config) and not isinstance(car_config, type):
        car_config = dataclasses.asdict(car_config)
    model = None
    if model_sha256 is not None or model_metadata is not None:
        model = {"sha256": model_sha256, "path": model_path, "metadata": model_metadata or {}}
    return {
        "command": command,
        "horizon": horizon,
        "car_config": car_config,
        "model": model,
        **extra,
    }
