"""``codecsplat selfcheck``: every Warp kernel on every available device against its float64 reference.

Each check runs one op forward and backward on a small random problem in float32 and float64, compares the
output and the input gradients with a float64 evaluation of the plain-torch reference on the CPU, and times
the forward+backward pass. The error is relative: max |got - ref| / max |ref|.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch

from .measure import format_table, time_call
from .ops import geometry
from .ops.raster import rasterize
from .reference import geometry as reference
from .reference.raster import rasterize_dense
from .synthetic import make_rig, random_gaussians, smooth_depth

TOLERANCE = {torch.float32: 1e-4, torch.float64: 1e-9}
"""Largest accepted relative error per dtype."""


@dataclass(frozen=True)
class KernelCheck:
    """An op, its reference, and a builder of float64 CPU inputs (the first ``num_grad`` are differentiated)."""

    name: str
    op: Callable[..., torch.Tensor]
    reference: Callable[..., torch.Tensor]
    make_inputs: Callable[[], tuple]
    num_grad: int


def _unproject_inputs():
    cams = make_rig(3, 64, 48)
    return smooth_depth(3, 48, 64), cams


def _reproject_inputs():
    cams = make_rig(3, 64, 48)
    return torch.randn(3, 8, 24, 32, dtype=torch.float64), smooth_depth(3, 24, 32), cams


def _cost_volume_inputs():
    cams = make_rig(3, 64, 48)
    return torch.randn(3, 8, 12, 16, dtype=torch.float64), geometry.inverse_depth_candidates(cams, 6), cams


def _raster_inputs(sh_degree=None):
    return (*random_gaussians(40, width=24, height=20, cameras=2, sh_degree=sh_degree), 24, 20)


CHECKS: list[KernelCheck] = [
    KernelCheck("unproject", geometry.unproject, reference.unproject_reference, _unproject_inputs, 1),
    KernelCheck(
        "reproject_average",
        lambda f, d, c: geometry.reproject_average(f, d, c)[0],
        lambda f, d, c: reference.reproject_average_reference(f, d, c, geometry.all_other_views(c.num_views, f.device))[0],
        _reproject_inputs,
        2,
    ),
    KernelCheck(
        "plane_sweep_cost_volume",
        geometry.plane_sweep_cost_volume,
        lambda f, d, c: reference.cost_volume_reference(f, d, c, geometry.all_other_views(c.num_views, f.device)),
        _cost_volume_inputs,
        1,
    ),
    KernelCheck("rasterize (RGB)", lambda *a: rasterize(*a)[0], lambda *a: rasterize_dense(*a)[0], _raster_inputs, 5),
    KernelCheck(
        "rasterize (SH deg 3, depth)",
        lambda *a: rasterize(*a)[1],
        lambda *a: rasterize_dense(*a)[1],
        lambda: _raster_inputs(sh_degree=3),
        5,
    ),
]


def _cast(inputs: Sequence, device: torch.device, dtype: torch.dtype) -> list:
    return [x.to(device=device, dtype=dtype) if hasattr(x, "to") else x for x in inputs]


def _forward_backward(fn, inputs: Sequence, num_grad: int, weights: torch.Tensor):
    leaves = [x.detach().requires_grad_() for x in inputs[:num_grad]]
    out = fn(*leaves, *inputs[num_grad:])
    grads = torch.autograd.grad((out * weights.to(out)).sum(), leaves, allow_unused=True)
    return out.detach(), [torch.zeros_like(x) if g is None else g for x, g in zip(leaves, grads)]


def _relative_error(got: torch.Tensor, ref: torch.Tensor) -> float:
    """max |got - ref| / max |ref| (absolute error when the reference is all zeros)."""
    return float((got.detach().cpu().double() - ref).abs().max() / ref.abs().max().clamp_min(1.0 if not ref.any() else 1e-30))


def run_check(check: KernelCheck, device: torch.device, dtype: torch.dtype, reps: int = 5) -> dict:
    """Errors and timing of one check on one device and dtype."""
    torch.manual_seed(0)
    base = check.make_inputs()
    ref_out, _ = _forward_backward(check.reference, base, check.num_grad, torch.ones(1, dtype=torch.float64))
    weights = torch.randn(ref_out.shape, dtype=torch.float64)
    ref_out, ref_grads = _forward_backward(check.reference, base, check.num_grad, weights)
    inputs = _cast(base, device, dtype)
    out, grads = _forward_backward(check.op, inputs, check.num_grad, weights)
    timing = time_call(lambda: _forward_backward(check.op, inputs, check.num_grad, weights), device, reps, warmup=1)
    err_out = _relative_error(out, ref_out)
    err_grad = max(_relative_error(g, r) for g, r in zip(grads, ref_grads))
    ok = max(err_out, err_grad) <= TOLERANCE[dtype]
    return {"kernel": check.name, "device": str(device), "dtype": str(dtype).replace("torch.", ""),
            "rel_err_out": err_out, "rel_err_grad": err_grad, "fwd_bwd_ms": timing.median_ms,
            "tolerance": TOLERANCE[dtype], "ok": ok}


COLUMNS = [
    ("kernel", "kernel", "s"), ("device", "device", "s"), ("dtype", "dtype", "s"),
    ("rel_err_out", "rel err out", ".2e"), ("rel_err_grad", "rel err grad", ".2e"),
    ("fwd_bwd_ms", "fwd+bwd ms", ".2f"), ("status", "status", "s"),
]


def run_selfcheck(devices: Sequence[torch.device], progress: bool = True) -> dict:
    """Run every check on every device in float32 and float64; returns rows, a table and overall ok."""
    from tqdm import tqdm

    jobs = [(c, d, t) for d in devices for c in CHECKS for t in (torch.float32, torch.float64)]
    rows = []
    for check, device, dtype in tqdm(jobs, desc="selfcheck", disable=not progress, leave=False):
        try:
            row = run_check(check, device, dtype)
            row["status"] = "ok" if row["ok"] else "FAIL"
        except Exception as exc:  # noqa: BLE001 - a kernel that cannot run on a device is a failed row, not a crash
            row = {"kernel": check.name, "device": str(device), "dtype": str(dtype).replace("torch.", ""),
                   "ok": False, "status": f"ERROR: {type(exc).__name__}: {exc}"[:160]}
        rows.append(row)
    return {"rows": rows, "table": format_table(rows, COLUMNS), "ok": all(r["ok"] for r in rows)}

