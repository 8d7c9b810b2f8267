"""`carrt-export CHECKPOINT -o policy.onnx --episodes DIR [DIR…] [--int8] [--fp16]`.

Exit codes: 0 written (and every requested variant written or skipped for lack of a
provider); 1 a check refused the model or a requested variant; 2 unusable input (no
checkpoint, no episodes). Errors are one line on stderr, like carrt's own commands.
"""

from __future__ import annotations

import argparse
import json
import sys

from carrt.errors import EXIT_USAGE, UserError

EXIT_REFUSED = 1


def build_parser() -> argparse.ArgumentParser:
    from export.onnx_export import DEFAULT_MAX_FRAMES, DEFAULT_TOLERANCE

    parser = argparse.ArgumentParser(
        prog="carrt-export",
        description="Export a trained policy checkpoint to one self-contained ONNX file "
        "that carrt accepts, checked for parity with PyTorch on recorded frames.",
    )
    parser.add_argument("checkpoint", help="policy checkpoint (.pt) written by training/")
    parser.add_argument("-o", "--out", required=True, help="output path, e.g. policy.onnx")
    parser.add_argument(
        "--episodes", nargs="+", required=True, metavar="DIR",
        help="episode directories (or directories of them): parity/calibration frames",
    )  # fmt: skip
    parser.add_argument("--int8", action="store_true", help="also write <out>.int8.onnx")
    parser.add_argument(
        "--int8-symmetric", action="store_true",
        help="int8 with zero-point-0 activations, as TensorRT requires (default: uint8 "
        "activations, best on onnxruntime's CPU)",
    )  # fmt: skip
    parser.add_argument(
        "--fp16", action="store_true", help="also write <out>.fp16.onnx (needs CUDA/TensorRT)"
    )
    parser.add_argument(
        "--tolerance", type=float, default=DEFAULT_TOLERANCE,
        help="max abs difference PyTorch vs ONNX on mu and sigma (default: %(default)g)",
    )  # fmt: skip
    parser.add_argument(
        "--max-frames", type=int, default=DEFAULT_MAX_FRAMES,
        help="recorded frames to check on (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--max-mean-mu-error", type=float, default=0.05,
        help="int8/fp16: largest mean |mu - mu_fp32| on held-out frames (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--max-abs-mu-error", type=float, default=0.2,
        help="int8/fp16: largest single |mu - mu_fp32| (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument(
        "--json-out", metavar="PATH",
        help="also write the report as JSON to PATH (carrt-train's report reads it)",
    )  # fmt: skip
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        from export.onnx_export import ExportRefused, export_policy

        report = export_policy(
            args.checkpoint, args.out, args.episodes, int8=args.int8, fp16=args.fp16,
            tolerance=args.tolerance, max_frames=args.max_frames,
            max_mean_mu_error=args.max_mean_mu_error, max_abs_mu_error=args.max_abs_mu_error,
            int8_symmetric=args.int8_symmetric,
        )  # fmt: skip
    except ExportRefused as exc:
        print(f"export: refused: {_line(exc)}", file=sys.stderr)
        return EXIT_REFUSED
    except UserError as exc:
        print(f"export: error: {_line(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130
    print(json.dumps(report.as_dict(), indent=2) if args.json else "\n".join(report.render()))
    if args.json_out:
        from pathlib import Path

        Path(args.json_out).write_text(json.dumps(report.as_dict(), indent=2, default=str) + "\n")
    refused = [v for v in report.variants.values() if not (v.written or v.skipped)]
    return EXIT_REFUSED if refused else 0


def _line(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return text


if __name__ == "__main__":
    sys.exit(main())
