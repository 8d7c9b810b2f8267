"""`carrt model info policy.onnx`: what is this model, and will this car run it?

Loads the model exactly as `carrt drive` would (same checks, same provider choice), so a model
that passes here is one the car accepts, and prints what a user needs in a bug report: the
metadata, the graph's inputs and outputs, size, sha256 (the id recorded in every episode)
and which execution provider runs it, with a warm-up latency on this machine.
"""

from __future__ import annotations

import argparse
import statistics
from typing import TYPE_CHECKING

from carrt.config import LoopConfig
from carrt.model_contract import format_shape

if TYPE_CHECKING:  # onnxruntime is imported only when the command runs (cli.py start-up)
    from carrt.policy import OnnxPolicy


def describe(policy: OnnxPolicy) -> list[str]:
    lines = [
        f"model     {policy.path}",
        f"size      {policy.size_bytes:,} bytes",
        f"sha256    {policy.sha256}",
    ]
    if policy.producer:
        lines.append(f"producer  {policy.producer}")
    lines.append(f"horizon   {policy.horizon} steps")
    names = max(len(t.name) for t in [*policy.inputs, *policy.outputs])
    for title, tensors in (("inputs", policy.inputs), ("outputs", policy.outputs)):
        lines.append(title)
        lines += [f"  {t.name:<{names}}  {t.dtype:<8} {format_shape(t.shape)}" for t in tensors]
    lines.append("metadata")
    width = max(len(k) for k in policy.metadata)
    lines += [f"  {key:<{width}}  {policy.metadata[key]}" for key in sorted(policy.metadata)]
    lines.append("providers")
    lines.append(f"  available  {', '.join(policy.available_providers)}")
    lines.append(f"  requested  {', '.join(policy.requested_providers)}")
    lines.append(f"  selected   {policy.provider}")
    if policy.fallback_note:
        lines.append(f"  note       {policy.fallback_note}")
    return lines


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("model", help="inspect an exported ONNX policy")
    commands = parser.add_subparsers(dest="model_command", required=True, metavar="ACTION")
    info = commands.add_parser(
        "info", help="metadata, inputs/outputs, sha256 and execution provider of a policy"
    )
    info.add_argument(
        "model",
        nargs="?",
        help="path to policy.onnx (without it: onnxruntime's version and the execution "
        "providers this machine offers, e.g. to check a Jetson's TensorRT/CUDA install)",
    )
    info.add_argument(
        "--providers",
        default=",".join(LoopConfig().providers),
        help="onnxruntime providers in order of preference, comma separated (default: %(default)s)",
    )
    info.add_argument(
        "--warmup", type=int, default=5, help="inferences to time on this machine (0: none)"
    )
    info.set_defaults(func=run)


def describe_runtime() -> list[str]:
    """What onnxruntime this machine has and which execution providers it offers."""
    import onnxruntime

    return [
        f"onnxruntime  {onnxruntime.__version__} ({onnxruntime.get_device()})",
        f"providers    {', '.join(onnxruntime.get_available_providers())}",
    ]


def run(args: argparse.Namespace) -> int:
    if args.model is None:
        print("\n".join(describe_runtime()))
        return 0
    from carrt.policy import OnnxPolicy

    providers = [p.strip() for p in str(args.providers).split(",") if p.strip()]
    # No control-period check here: describing a model must not depend on a car's config.
    policy = OnnxPolicy(args.model, providers=providers, control_period_s=None)
    lines = describe(policy)
    warmup = getattr(args, "warmup", 0)
    if warmup > 0:
        ms = [t * 1e3 for t in policy.warm_up(warmup)]
        lines.append(
            f"warm-up   {warmup} runs: first {ms[0]:.2f} ms, "
            f"median {statistics.median(ms):.2f} ms, last {ms[-1]:.2f} ms"
        )
    print("\n".join(lines))
    return 0
