"""Graph-level fix-ups and the checks every written file passes (fp32 and variants alike).

Each check raises ExportRefused with one line naming the problem; write_checked puts a file in
place only after its check passed, so a refused model never appears under its final name.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from pathlib import Path

import onnx
from onnx.external_data_helper import uses_external_data

from carrt import model_contract as mc
from carrt.errors import UserError
from firmware_bridge.timing import CONTROL_PERIOD_S

OPSET = 17  # what TensorRT 8.6 (JetPack 5) parses
CPU = "CPUExecutionProvider"


class ExportRefused(UserError):
    """The exported model failed a check; nothing was written at the output path."""


def set_metadata(model: onnx.ModelProto, meta: dict[str, str]) -> None:
    del model.metadata_props[:]
    for key in sorted(meta):
        model.metadata_props.add(key=key, value=str(meta[key]))


def get_metadata(model: onnx.ModelProto) -> dict[str, str]:
    return {p.key: p.value for p in model.metadata_props}


def positive_perms(graph: onnx.GraphProto) -> None:
    """Transpose perms as the spec writes them (0..r-1).

    torch's TorchScript exporter turns `movedim(-1, -3)` into a Transpose with negative perm
    entries; onnxruntime tolerates them, the ONNX checker and TensorRT's parser do not.
    """
    for node in graph.node:
        for attr in node.attribute:
            if (
                node.op_type == "Transpose"
                and attr.name == "perm"
                and min(attr.ints, default=0) < 0
            ):
                rank = len(attr.ints)
                attr.ints[:] = [p % rank for p in attr.ints]
            for sub in [*([attr.g] if attr.HasField("g") else []), *attr.graphs]:
                positive_perms(sub)


def declare_outputs(model: onnx.ModelProto, horizon: int) -> None:
    """Declare mu/sigma as [N, H, 2]: the tracer leaves H symbolic, which hides the horizon
    from `carrt model info` and costs TensorRT a dynamic dim. Parity proves the values."""
    for value in model.graph.output:
        if value.name in (mc.OUTPUT_MU, mc.OUTPUT_SIGMA):
            dims = value.type.tensor_type.shape.dim
            for dim, want in zip(dims[1:], (horizon, 2), strict=True):
                dim.Clear()
                dim.dim_value = want


def tidy_opsets(model: onnx.ModelProto) -> None:
    """Drop opset imports no node uses (onnxruntime's optimiser lists all its own)."""
    used = {n.domain for n in model.graph.node} | {"", "ai.onnx"}
    keep = [o for o in model.opset_import if o.domain in used]
    del model.opset_import[:]
    model.opset_import.extend(keep)


def external_tensors(model: onnx.ModelProto) -> list[str]:
    """Names of tensors stored outside the file (initializers, Constant attrs, subgraphs)."""
    found: list[str] = []

    def graph(g: onnx.GraphProto) -> None:
        tensors = [*g.initializer, *(s.values for s in g.sparse_initializer)]
        for node in g.node:
            for attr in node.attribute:
                tensors += [attr.t] if attr.HasField("t") else []
                tensors += list(attr.tensors)
                for sub in [*([attr.g] if attr.HasField("g") else []), *attr.graphs]:
                    graph(sub)
        found.extend(t.name or "<unnamed>" for t in tensors if uses_external_data(t))

    graph(model.graph)
    return found


def check_structure(model: onnx.ModelProto, horizon: int) -> None:
    """Checks that need no runtime. Raises ExportRefused naming the problem."""
    outside = external_tensors(model)
    if outside:
        raise ExportRefused(
            f"{len(outside)} tensors use external data ({', '.join(outside[:3])}): the file "
            "would not be self-contained"
        )
    foreign = sorted({n.domain for n in model.graph.node if n.domain not in ("", "ai.onnx")})
    if foreign:
        raise ExportRefused(
            f"graph uses operators from {', '.join(foreign)}, outside standard ONNX "
            "(TensorRT and other runtimes cannot run them)"
        )
    opsets = {o.domain or "ai.onnx": o.version for o in model.opset_import}
    if opsets.get("ai.onnx") != OPSET:
        raise ExportRefused(f"graph uses opset {opsets.get('ai.onnx')}, expected {OPSET}")
    try:
        onnx.checker.check_model(model, full_check=True)
    except (onnx.checker.ValidationError, onnx.shape_inference.InferenceError) as exc:
        raise ExportRefused(f"ONNX checker: {' '.join(str(exc).split())[:200]}") from exc
    try:
        mc.validate_metadata(get_metadata(model), CONTROL_PERIOD_S)
        mc.validate_io(*_declared_io(model), horizon)
    except mc.ContractError as exc:
        raise ExportRefused(f"violates carrt's model contract: {exc}") from exc


_NP = {onnx.TensorProto.UINT8: "uint8", onnx.TensorProto.FLOAT: "float32"}


def _declared_io(model: onnx.ModelProto) -> tuple[list[mc.TensorSpec], list[mc.TensorSpec]]:
    def spec(value: onnx.ValueInfoProto) -> mc.TensorSpec:
        t = value.type.tensor_type
        dims = tuple(d.dim_value if d.HasField("dim_value") else d.dim_param or None
                     for d in t.shape.dim)  # fmt: skip
        return mc.TensorSpec(value.name, _NP.get(t.elem_type, str(t.elem_type)), dims)

    inits = {i.name for i in model.graph.initializer}
    inputs = [spec(v) for v in model.graph.input if v.name not in inits]
    return inputs, [spec(v) for v in model.graph.output]


def carrt_accepts(path: Path) -> None:
    """Load `path` exactly as `carrt drive` would, on the CPU, and run it on a grey frame."""
    from carrt.policy import OnnxPolicy

    try:
        OnnxPolicy(path, providers=[CPU], intra_op_threads=1).warm_up(2)
    except UserError as exc:
        raise ExportRefused(f"carrt refuses the exported file: {exc}") from exc


def write_checked(model: onnx.ModelProto, out: Path, check: Callable[[Path], None]) -> int:
    """Serialize to a temporary name beside `out`, run `check` on it, then rename into place.

    Returns the size. On any failure the temporary file is removed and `out` is untouched.
    """
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    try:
        data = model.SerializeToString()
        with tmp.open("wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        check(tmp)
        os.replace(tmp, out)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    return len(data)


def topological_sort(graph: onnx.GraphProto) -> None:
    """Reorder nodes so each comes after the producers of its inputs (the ONNX rule)."""
    ready = {i.name for i in graph.input} | {i.name for i in graph.initializer} | {""}
    pending, ordered = list(graph.node), []
    while pending:
        rest = [n for n in pending if not set(n.input) <= ready]
        done = [n for n in pending if set(n.input) <= ready]
        if not done:  # a cycle or a dangling input: leave it for the checker to name
            ordered += rest
            break
        for node in done:
            ready.update(node.output)
        ordered += done
        pending = rest
    del graph.node[:]
    graph.node.extend(ordered)
