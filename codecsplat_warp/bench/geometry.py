"""``codecsplat bench geometry``: reproject_average (Warp) against the torch ``grid_sample`` reference.

Shapes mirror the model's use: RE10K (2 views, C=64, 64x64 and 256x256 grids of a 256x256 image) and DL3DV
(8 views, C=64, 64x112 and 256x448 grids of a 256x448 image), float32. For each shape and implementation:
median ms of forward and forward+backward, peak memory of forward+backward, and the error of the float32
result against a float64 evaluation of the same op (max abs of the output; relative L2 of the gradients).
"""

from __future__ import annotations

import argparse

import torch

from ..checks import set_validation, validation_enabled
from ..errors import InputError
from ..measure import cuda_peak_bytes, format_table, machine_name, rss_peak_growth_bytes, time_call
from ..ops.geometry import all_other_views, reproject_average
from ..reference.geometry import reproject_average_reference
from ..synthetic import make_rig, smooth_depth
from .options import GEOMETRY_SHAPES as SHAPES
from .options import GeometryShape as Shape


IMPLEMENTATIONS = ("warp", "torch")


def run(args: argparse.Namespace) -> dict:
    device = torch.device(args.device)
    reps = args.reps or (30 if device.type == "cuda" else 3)
    unknown = [s for s in args.shapes.split(",") if s not in SHAPES]
    if unknown:
        raise InputError(f"unknown shape {unknown[0]!r}; choose from {', '.join(SHAPES)}")
    shapes = [SHAPES[s] for s in args.shapes.split(",")]
    previous = validation_enabled()
    set_validation(args.validate == "on")
    rows = []
    try:
        for shape in shapes:
            for impl in IMPLEMENTATIONS:
                rows.append(measure(shape, impl, device, reps))
                _print_row(rows[-1])
    finally:
        set_validation(previous)
    for shape in shapes:
        warp_row, torch_row = (next(r for r in rows if r["shape"] == shape.name and r["impl"] == i) for i in IMPLEMENTATIONS)
        warp_row["speedup_fwd_bwd"] = torch_row["fwd_bwd_ms"] / warp_row["fwd_bwd_ms"]
        warp_row["memory_ratio"] = (warp_row["peak_mib"] / torch_row["peak_mib"]) if torch_row["peak_mib"] else None
        warp_row["memory_ratio_fwd"] = (
            warp_row["peak_fwd_mib"] / torch_row["peak_fwd_mib"]) if torch_row["peak_fwd_mib"] else None
    table = format_table(rows, COLUMNS)
    print(f"\nreproject_average, float32, input checks {args.validate}, {machine_name(device)}\n{table}")
    return {"benchmark": "geometry", "validate": args.validate, "device": str(device), "machine": machine_name(device), "rows": rows, "table": table}


COLUMNS = [
    ("shape", "shape", "s"),
    ("impl", "impl", "s"),
    ("fwd_ms", "fwd ms", ".3f"),
    ("fwd_bwd_ms", "fwd+bwd ms", ".3f"),
    ("peak_fwd_mib", "fwd peak MiB", ".1f"),
    ("peak_mib", "fwd+bwd peak MiB", ".1f"),
    ("max_err_fwd", "max err fwd", ".2e"),
    ("validity_flips", "validity flips", "d"),
    ("rel_err_grad", "rel err grad", ".2e"),
    ("speedup_fwd_bwd", "speed-up fwd+bwd", ".2f"),
    ("memory_ratio_fwd", "memory ratio fwd", ".3f"),
    ("memory_ratio", "memory ratio fwd+bwd", ".3f"),
]


def _print_row(row: dict) -> None:
    print(f"  {row['shape']:<10} {row['impl']:<6} fwd {row['fwd_ms']:9.3f} ms  fwd+bwd {row['fwd_bwd_ms']:9.3f} ms  "
          f"peak {row['peak_mib']:8.1f} MiB  err {row['max_err_fwd']:.2e}", flush=True)


def make_inputs(shape: Shape, device: torch.device, dtype=torch.float32):
    """Cameras at image size, features, depths and fixed output weights for one shape."""
    cams = make_rig(shape.views, shape.image_w, shape.image_h, dtype=dtype, device=device)
    g = torch.Generator().manual_seed(3)
    feat = torch.randn(shape.views, shape.channels, shape.grid_h, shape.grid_w, generator=g, dtype=torch.float64)
    weights = torch.randn(feat.shape, generator=g, dtype=torch.float64)
    depth = smooth_depth(shape.views, shape.grid_h, shape.grid_w)
    return cams, feat.to(device, dtype), depth.to(device, dtype), weights.to(device, dtype)


def _op(impl: str):
    """(feat, depth, cams) -> (avg, count) for one implementation."""
    if impl == "warp":
        return lambda f, d, cams: reproject_average(f, d, cams)
    return lambda f, d, cams: reproject_average_reference(f, d, cams, all_other_views(cams.num_views, f.device))


def _forward_backward(impl: str, cams, feat, depth, weights):
    feat = feat.detach().requires_grad_()
    depth = depth.detach().requires_grad_()
    out, count = _op(impl)(feat, depth, cams)
    grads = torch.autograd.grad(out, (feat, depth), grad_outputs=weights)  # d(sum(out * weights)), no temporaries
    return out.detach(), count, grads


def measure(shape: Shape, impl: str, device: torch.device, reps: int) -> dict:
    """Timings, peak memory and float32-vs-float64 errors for one shape and implementation."""
    cams, feat, depth, weights = make_inputs(shape, device)
    op = _op(impl)
    with torch.no_grad():
        fwd = time_call(lambda: op(feat, depth, cams), device, reps)
    fwd_bwd = time_call(lambda: _forward_backward(impl, cams, feat, depth, weights), device, reps)
    peak_fwd = _peak_bytes(shape, impl, device, backward=False)
    peak = _peak_bytes(shape, impl, device, backward=True)
    out, count, grads = _forward_backward(impl, cams, feat, depth, weights)
    ref_out, ref_count, ref_grads = _float64_reference(shape, device)
    grad_err = max(float((g.double() - r).norm() / r.norm().clamp_min(1e-30)) for g, r in zip(grads, ref_grads))
    # A sample whose projection lies within rounding of the image border can be valid in float64 and not in
    # float32: the average then jumps by design. Such validity flips are counted, not mixed into the error.
    same_count = (count == ref_count)[:, None].expand_as(out)
    return {
        "shape": shape.name, "impl": impl, "views": shape.views, "channels": shape.channels,
        "grid": f"{shape.grid_h}x{shape.grid_w}", "fwd_ms": fwd.median_ms, "fwd_bwd_ms": fwd_bwd.median_ms,
        "fwd_spread_ms": [fwd.min_ms, fwd.max_ms], "fwd_bwd_spread_ms": [fwd_bwd.min_ms, fwd_bwd.max_ms], "reps": reps,
        "peak_fwd_mib": peak_fwd / 2**20, "peak_mib": peak / 2**20, "max_err_fwd": float((out.double() - ref_out)[same_count].abs().max()),
        "validity_flips": int((count != ref_count).sum()), "rel_err_grad": grad_err,
    }


_reference_cache: dict = {}


def _float64_reference(shape: Shape, device: torch.device):
    """Output and gradients in float64 (Warp float64 kernels; tests tie them to the torch reference)."""
    key = (shape, str(device))
    if key not in _reference_cache:
        cams, feat, depth, weights = make_inputs(shape, device, torch.float64)
        _reference_cache.clear()
        _reference_cache[key] = _forward_backward("warp", cams, feat, depth, weights)
    return _reference_cache[key]


def _peak_bytes(shape: Shape, impl: str, device: torch.device, backward: bool) -> int:
    """Peak memory of one forward (inference, no autograd) or one forward+backward, above the inputs."""
    cams, feat, depth, weights = make_inputs(shape, device)
    op = _op(impl)

    def forward():
        with torch.no_grad():
            return op(feat, depth, cams)

    call = (lambda: _forward_backward(impl, cams, feat, depth, weights)) if backward else forward
    call()  # camera arrays memoized, kernels loaded: measure the steady state
    if device.type == "cuda":
        return cuda_peak_bytes(call, device)
    return rss_peak_growth_bytes(call)
