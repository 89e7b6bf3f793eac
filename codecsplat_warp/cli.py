"""The ``codecsplat`` command line.

Exit codes: 0 success, 1 user error (bad arguments or input, reported as one line without a traceback),
2 internal error (a bug: the traceback is printed). Every command takes ``--device cpu|cuda|auto`` and
``--json`` (machine-readable result on stdout instead of the human table).
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import traceback

from .errors import CodecSplatError

EXIT_OK, EXIT_USER, EXIT_INTERNAL = 0, 1, 2

BENCHMARKS = {
    "geometry": "codecsplat_warp.bench.geometry",
    "raster": "codecsplat_warp.bench.raster",
}
"""``codecsplat bench NAME`` -> module with ``add_arguments(parser)`` and ``run(args) -> dict``."""


class UsageError(CodecSplatError):
    """The command line itself is wrong (unknown option, missing argument)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse would exit with 2, which we reserve for internal errors
        raise UsageError(f"{self.prog.split()[-1]}: {message}" if " " in self.prog else message)


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (CUDA when available)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="codecsplat", description="CodecSplat on NVIDIA Warp: kernels, benchmarks and tools.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    selfcheck = sub.add_parser("selfcheck", help="every kernel vs its float64 reference (--device auto: every device)")
    _common(selfcheck)

    bench = sub.add_parser("bench", help="benchmarks (tables on stdout, JSON with --out)")
    bench_sub = bench.add_subparsers(dest="benchmark", required=True, parser_class=_Parser)
    for name, module in BENCHMARKS.items():
        p = bench_sub.add_parser(name, help=f"{name} benchmark")
        _common(p)
        p.add_argument("--out", help="write the JSON result to this file")
        importlib.import_module(module).add_arguments(p)
    return parser


def _cmd_selfcheck(args) -> int:
    from .device import available_devices, resolve_device
    from .selfcheck import run_selfcheck

    devices = available_devices() if args.device == "auto" else [resolve_device(args.device)]
    result = run_selfcheck(devices, progress=not args.json)
    if args.json:
        print(json.dumps({k: v for k, v in result.items() if k != "table"}, indent=2))
    else:
        print(result["table"])
        print("\nselfcheck: " + ("all kernels agree with their float64 references" if result["ok"] else "FAILED"))
    return EXIT_OK if result["ok"] else EXIT_INTERNAL


def _cmd_bench(args) -> int:
    from .bench.common import write_json
    from .device import resolve_device

    args.device = str(resolve_device(args.device))
    result = importlib.import_module(BENCHMARKS[args.benchmark]).run(args)
    if args.out:
        write_json(args.out, result)
    if args.json:
        print(json.dumps(result, indent=2))
    return EXIT_OK


COMMANDS = {"selfcheck": _cmd_selfcheck, "bench": _cmd_bench}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``codecsplat`` console script; returns the exit code."""
    try:
        args = build_parser().parse_args(argv)
        return COMMANDS[args.command](args)
    except CodecSplatError as exc:
        print(f"codecsplat: error: {exc}", file=sys.stderr)
        return EXIT_USER
    except KeyboardInterrupt:
        print("codecsplat: interrupted", file=sys.stderr)
        return 130
    except Exception:  # noqa: BLE001 - anything else is a bug: show it
        traceback.print_exc()
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
