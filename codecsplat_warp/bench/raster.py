"""``codecsplat bench raster``: the Warp Gaussian rasterizer against gsplat 1.5.3 and the dense torch reference.

Workloads mirror the model's use (issue 3): pixel-aligned Gaussians unprojected from context views with a
smooth random depth field in [1.5, 9], per-axis scale ``depth / f * U(0.6, 1.4)``, random rotations, opacity
``U(0.3, 1)`` and RGB colours, rendered into one target camera near the context views, float32:

* ``re10k``: 2 views x 256x256 = 131,072 Gaussians -> 256x256;
* ``dl3dv``: 8 views x 256x448 = 917,504 Gaussians -> 256x448.

For each workload: median ms of forward (no grad) and forward+backward (loss = weighted sum of rgb and
depth), peak memory of forward+backward (CUDA: torch allocator delta, Warp's own pool reported apart; CPU:
peak RSS growth in a fresh process), intersection count, and -- on CUDA with gsplat importable --
gsplat's ``rasterization(packed=False, render_mode="RGB+ED")`` on the same inputs, its times (ours and gsplat's
calls timed in interleaved rounds), the PSNR of our RGB against its RGB and the smallest cosine, over the five
Gaussian arguments, between our gradients and gsplat's (:func:`gradient_cosine`). A small scene is also compared with
the dense torch reference (time and max error).
On the CPU (gsplat has no CPU rasterizer) each workload is timed, in interleaved rounds, in three ways: the tile
layout on one thread and on every thread of ``--threads`` (default: every available core), and the block layout on
one thread, the CUDA kernels run with one-lane blocks (the CPU rasterizer before the tile layout, see
:data:`~codecsplat_warp.ops.raster.CPU_LAYOUTS`), against which the speed-ups are given; peak memory is that of the
tile layout on every thread.
``--scale`` keeps a random fraction of the Gaussians (quick CPU runs). ``--kernels N`` (CUDA) also lists the N
kernels with the most GPU time per call for ours and gsplat's forward and forward+backward, from
``torch.profiler`` (stored per workload under ``kernels``).
"""

from __future__ import annotations

import argparse
import traceback

import torch
import warp as wp

from ..measure import (
    cuda_kernel_times, cuda_peak_bytes, format_table, interleaved_medians, machine_name, rss_peak_growth_bytes,
    time_call,
)  # fmt: skip
from ..device import cpu_threads, set_cpu_threads
from ..metrics.image import psnr
from ..ops.raster import GAUSSIAN_ARGUMENTS, cpu_layout, rasterize
from ..reference.raster import rasterize_dense
from ..synthetic import make_rig, smooth_depth
from .options import WORKLOADS, Workload


REFERENCE_WORKLOAD = Workload("dense-ref", 1, 40, 40)
"""Small scene (1,600 Gaussians, 40x40) where the dense O(HWN) torch reference is affordable."""


def run(args: argparse.Namespace) -> dict:
    device = torch.device(args.device)
    reps = args.reps or (30 if device.type == "cuda" else 3)
    scale = float(getattr(args, "scale", 1.0))
    if not 0 < scale <= 1:
        raise ValueError(f"--scale must be in (0, 1], got {scale}")
    gsplat = None if getattr(args, "no_gsplat", False) else _import_gsplat(device)
    rows = []
    for name in args.workloads.split(","):
        if name not in WORKLOADS:
            raise ValueError(f"unknown workload {name!r}; choose from {', '.join(WORKLOADS)}")
        if device.type == "cpu":
            rows += measure_cpu_layouts(WORKLOADS[name], reps, scale)
        else:
            rows.append(measure_workload(WORKLOADS[name], device, reps, scale, gsplat))
        _print_row(rows[-1])
        if getattr(args, "kernels", 0) and device.type == "cuda":
            rows[-1]["kernels"] = measure_kernels(WORKLOADS[name], device, reps, scale, gsplat, args.kernels)
    reference = measure_reference(device, reps)
    machine = machine_name(device)
    table = format_table(rows, CPU_COLUMNS if device.type == "cpu" else COLUMNS)
    ref_table = format_table([reference], REFERENCE_COLUMNS)
    gsplat_note = "gsplat: " + (gsplat["status"] if gsplat else "skipped (--no-gsplat)")
    print(f"\nrasterize, float32, {machine}\n{gsplat_note}\n{table}\n\ndense torch reference, small scene\n{ref_table}")
    return {
        "benchmark": "raster", "device": str(device), "machine": machine, "reps": reps, "scale": scale,
        "gsplat": gsplat["status"] if gsplat else "skipped", "rows": rows, "reference": reference,
        "table": table, "reference_table": ref_table,
    }  # fmt: skip


COLUMNS = [
    ("workload", "workload", "s"),
    ("gaussians", "Gaussians", ",d"),
    ("size", "image", "s"),
    ("intersections", "intersections", ",d"),
    ("fwd_ms", "fwd ms", ".3f"),
    ("fwd_bwd_ms", "fwd+bwd ms", ".3f"),
    ("peak_mib", "peak MiB", ".1f"),
    ("gsplat_fwd_ms", "gsplat fwd ms", ".3f"),
    ("gsplat_fwd_bwd_ms", "gsplat fwd+bwd ms", ".3f"),
    ("gsplat_peak_mib", "gsplat peak MiB", ".1f"),
    ("ratio_fwd", "fwd / gsplat", ".2f"),
    ("ratio_fwd_bwd", "fwd+bwd / gsplat", ".2f"),
    ("psnr_vs_gsplat_db", "PSNR vs gsplat dB", ".1f"),
    ("grad_cosine_vs_gsplat", "grad cosine vs gsplat", ".6f"),
]

CPU_COLUMNS = [
    ("workload", "workload", "s"),
    ("gaussians", "Gaussians", ",d"),
    ("size", "image", "s"),
    ("intersections", "intersections", ",d"),
    ("layout", "layout", "s"),
    ("threads", "threads", "d"),
    ("fwd_ms", "fwd ms", ".1f"),
    ("fwd_bwd_ms", "fwd+bwd ms", ".1f"),
    ("fwd_speedup", "fwd speed-up", ".1f"),
    ("fwd_bwd_speedup", "fwd+bwd speed-up", ".1f"),
    ("peak_mib", "peak MiB", ".1f"),
]

BASELINE_LAYOUT = "blocks"
"""The CPU layout the speed-ups are given against (on one thread): the CPU rasterizer before the tile layout."""

REFERENCE_COLUMNS = [
    ("gaussians", "Gaussians", ",d"),
    ("size", "image", "s"),
    ("fwd_ms", "warp fwd ms", ".3f"),
    ("fwd_bwd_ms", "warp fwd+bwd ms", ".3f"),
    ("dense_fwd_ms", "dense fwd ms", ".3f"),
    ("dense_fwd_bwd_ms", "dense fwd+bwd ms", ".3f"),
    ("max_abs_err_rgb", "max |rgb err|", ".2e"),
    ("max_rel_err_grad", "max rel grad err", ".2e"),
]


def make_scene(workload: Workload, device: torch.device, scale: float = 1.0, seed: int = 0) -> dict:
    """Pixel-aligned Gaussians of ``workload`` and its target camera (float32 on ``device``).

    Returns a dict of ``means, quats, scales, opacities, colors`` ([N,...]), ``viewmats`` [1,4,4], ``Ks`` [1,3,3],
    ``width``, ``height`` and fixed loss weights ``w_rgb`` [1,H,W,3], ``w_depth`` [1,H,W,1].
    """
    V, H, W = workload.views, workload.height, workload.width
    cams = make_rig(V, W, H, seed=seed)
    depth = smooth_depth(V, H, W, seed=seed + 1, lo=1.5, hi=9.0)
    g = torch.Generator().manual_seed(seed + 2)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    pixels = torch.stack([u + 0.5, v + 0.5, torch.ones_like(u)], dim=-1).reshape(1, -1, 3)
    rays = pixels @ torch.linalg.inv(cams.K).transpose(-1, -2)
    points_cam = rays * depth.reshape(V, -1, 1)
    c2w = cams.c2w
    means = (points_cam @ c2w[:, :3, :3].transpose(-1, -2) + c2w[:, None, :3, 3]).reshape(-1, 3)
    focal = cams.K[:, 0, 0].reshape(V, 1, 1)
    scales = (depth.reshape(V, -1, 1) / focal).reshape(-1, 1) * (0.6 + 0.8 * torch.rand(V * H * W, 3, generator=g, dtype=torch.float64))
    N = means.shape[0]
    quats = torch.nn.functional.normalize(torch.randn(N, 4, generator=g, dtype=torch.float64), dim=-1)
    opacities = 0.3 + 0.7 * torch.rand(N, generator=g, dtype=torch.float64)
    colors = torch.rand(N, 3, generator=g, dtype=torch.float64)
    keep = torch.randperm(N, generator=g)[: max(1, round(scale * N))].sort().values if scale < 1 else slice(None)
    target = make_rig(1, W, H, seed=seed + 3, offset=(0.05, -0.03, -0.1))
    scene = {
        "means": means[keep], "quats": quats[keep], "scales": scales[keep], "opacities": opacities[keep],
        "colors": colors[keep], "viewmats": target.w2c, "Ks": target.K,
        "w_rgb": torch.rand(1, H, W, 3, generator=g, dtype=torch.float64),
        "w_depth": torch.rand(1, H, W, 1, generator=g, dtype=torch.float64) * 0.1,
    }  # fmt: skip
    scene = {k: t.to(device=device, dtype=torch.float32).contiguous() for k, t in scene.items()}
    scene.update(width=W, height=H)
    return scene


def _splat_args(scene: dict, requires_grad: bool) -> list:
    tensors = [scene[k].detach().requires_grad_(requires_grad) for k in GAUSSIAN_ARGUMENTS]
    return [*tensors, scene["viewmats"], scene["Ks"]]


def ours_forward(scene: dict):
    with torch.no_grad():
        return rasterize(*_splat_args(scene, False), scene["width"], scene["height"])


def ours_forward_backward(scene: dict):
    args = _splat_args(scene, True)
    rgb, depth, _, _ = rasterize(*args, scene["width"], scene["height"])
    loss = (rgb * scene["w_rgb"]).sum() + (depth * scene["w_depth"]).sum()
    return torch.autograd.grad(loss, args[:5])


def gsplat_forward(gsplat, scene: dict):
    with torch.no_grad():
        return _gsplat_render(gsplat, _splat_args(scene, False), scene)


def gsplat_forward_backward(gsplat, scene: dict):
    args = _splat_args(scene, True)
    render = _gsplat_render(gsplat, args, scene)
    loss = (render[..., :3] * scene["w_rgb"]).sum() + (render[..., 3:] * scene["w_depth"]).sum()
    return torch.autograd.grad(loss, args[:5])


def gradient_cosine(ours: tuple[torch.Tensor, ...], theirs: tuple[torch.Tensor, ...]) -> float:
    """The smallest cosine, over the arguments, between two sets of gradients (each argument's gradient flattened,
    in float64): 1 when every argument's gradient points the same way."""
    return min(float(torch.nn.functional.cosine_similarity(a.double().flatten(), b.double().flatten(), dim=0))
               for a, b in zip(ours, theirs, strict=True))  # fmt: skip


def _gsplat_render(gsplat, args: list, scene: dict) -> torch.Tensor:
    render, _, _ = gsplat["rasterization"](
        *args, scene["width"], scene["height"], near_plane=0.01, far_plane=1e10, packed=False,
        render_mode="RGB+ED", rasterize_mode="classic",
    )  # fmt: skip
    return render


def measure_workload(workload: Workload, device: torch.device, reps: int, scale: float, gsplat: dict | None) -> dict:
    """Timings, memory and (with gsplat) the comparison for one workload; errors are recorded, not raised.

    Ours and gsplat's forward and forward+backward are timed in interleaved rounds
    (:func:`~codecsplat_warp.measure.interleaved_medians`), so that a lent machine's drifting host speed
    moves both sides of a ratio alike."""
    scene = make_scene(workload, device, scale)
    row = {"workload": workload.name, "gaussians": scene["means"].shape[0], "size": f"{workload.height}x{workload.width}",
           "reps": reps}  # fmt: skip
    calls = {"fwd_ms": lambda: ours_forward(scene), "fwd_bwd_ms": lambda: ours_forward_backward(scene)}
    try:
        rgb, _, _, meta = ours_forward(scene)
        row["intersections"] = meta.intersection_count
        ours_grads = ours_forward_backward(scene)
    except Exception as exc:  # noqa: BLE001 - a benchmark reports failures and goes on
        row["error"] = f"warp: {type(exc).__name__}: {exc}"
        traceback.print_exc()
        return row
    if gsplat is not None and gsplat.get("rasterization") is not None:
        try:
            theirs = gsplat_forward(gsplat, scene)[..., :3]
            row["grad_cosine_vs_gsplat"] = gradient_cosine(ours_grads, gsplat_forward_backward(gsplat, scene))
            row["psnr_vs_gsplat_db"] = float(psnr(rgb.permute(0, 3, 1, 2), theirs.permute(0, 3, 1, 2), clip=False))
            calls.update(gsplat_fwd_ms=lambda: gsplat_forward(gsplat, scene),
                         gsplat_fwd_bwd_ms=lambda: gsplat_forward_backward(gsplat, scene))  # fmt: skip
        except Exception as exc:  # noqa: BLE001
            row["error"] = f"gsplat: {type(exc).__name__}: {exc}"
            traceback.print_exc()
    row.update(interleaved_medians(calls, device, reps))
    row.update(_peak_memory(device, scene))
    if "gsplat_fwd_ms" in row:
        row["gsplat_peak_mib"] = cuda_peak_bytes(lambda: gsplat_forward_backward(gsplat, scene), device) / 2**20
        row["ratio_fwd"] = row["fwd_ms"] / row["gsplat_fwd_ms"]
        row["ratio_fwd_bwd"] = row["fwd_bwd_ms"] / row["gsplat_fwd_bwd_ms"]
    return row


def measure_cpu_layouts(workload: Workload, reps: int, scale: float) -> list[dict]:
    """CPU rows of ``workload``: the tile layout on one thread and on :func:`~codecsplat_warp.device.cpu_threads`
    threads, the block layout on one thread, each timed forward and forward+backward in interleaved rounds, with
    speed-ups against the block layout; errors are recorded, not raised."""
    device = torch.device("cpu")
    scene = make_scene(workload, device, scale)
    threads = cpu_threads()
    configs = [("tiles", 1), ("tiles", threads), (BASELINE_LAYOUT, 1)] if threads > 1 else \
        [("tiles", 1), (BASELINE_LAYOUT, 1)]  # fmt: skip
    common = {"workload": workload.name, "gaussians": scene["means"].shape[0], "size": f"{workload.height}x{workload.width}",
              "reps": reps}  # fmt: skip
    calls = {}
    for layout, count in configs:
        for key, fn in (("fwd_ms", ours_forward), ("fwd_bwd_ms", ours_forward_backward)):
            calls[layout, count, key] = _configured(fn, scene, layout, count)
    try:
        common["intersections"] = calls["tiles", threads, "fwd_ms"]()[3].intersection_count
        peak = rss_peak_growth_bytes(calls["tiles", threads, "fwd_bwd_ms"]) / 2**20  # before freed memory piles up
        medians = interleaved_medians(calls, device, reps)
    except Exception as exc:  # noqa: BLE001 - a benchmark reports failures and goes on
        traceback.print_exc()
        return [{**common, "error": f"warp: {type(exc).__name__}: {exc}"}]
    finally:
        set_cpu_threads(threads)
    rows = []
    for layout, count in configs:
        row = {**common, "layout": layout, "threads": count, "fwd_ms": medians[layout, count, "fwd_ms"],
               "fwd_bwd_ms": medians[layout, count, "fwd_bwd_ms"]}  # fmt: skip
        for key in ("fwd", "fwd_bwd"):
            row[f"{key}_speedup"] = medians[BASELINE_LAYOUT, 1, f"{key}_ms"] / row[f"{key}_ms"]
        if (layout, count) == ("tiles", threads):
            row["peak_mib"] = peak
        rows.append(row)
    return rows


def _configured(fn, scene: dict, layout: str, threads: int):
    """``fn(scene)`` in CPU layout ``layout`` on ``threads`` threads."""

    def call():
        set_cpu_threads(threads)
        with cpu_layout(layout):
            return fn(scene)

    return call


def measure_kernels(workload: Workload, device: torch.device, reps: int, scale: float, gsplat: dict | None,
                    top: int) -> dict:  # fmt: skip
    """Per-kernel GPU time of ours (and gsplat's) forward and forward+backward on ``workload``
    (:func:`~codecsplat_warp.measure.cuda_kernel_times`): ``{"ours fwd": {"total_us": .., "kernels": [[name,
    us, launches], ...top]}, ...}``, printed as it goes."""
    scene = make_scene(workload, device, scale)
    calls = {"ours fwd": lambda: ours_forward(scene), "ours fwd+bwd": lambda: ours_forward_backward(scene)}
    if gsplat is not None and gsplat.get("rasterization") is not None:
        calls.update({"gsplat fwd": lambda: gsplat_forward(gsplat, scene),
                      "gsplat fwd+bwd": lambda: gsplat_forward_backward(gsplat, scene)})
    result = {}
    for case, call in calls.items():
        times = cuda_kernel_times(call, device, reps)
        result[case] = {"total_us": sum(us for _, us, _ in times), "kernels": [list(t) for t in times[:top]]}
        print(f"  {workload.name} {case}: {result[case]['total_us']:.1f} us of GPU time per call", flush=True)
        for name, us, launches in times[:top]:
            print(f"    {us:9.1f} us  x{launches:4.1f}  {name[:100]}", flush=True)
    return result


def measure_reference(device: torch.device, reps: int) -> dict:
    """Warp vs the dense torch reference on a small scene: times and agreement (float32)."""
    scene = make_scene(REFERENCE_WORKLOAD, device)
    W, H = scene["width"], scene["height"]
    row = {"gaussians": scene["means"].shape[0], "size": f"{H}x{W}"}
    try:
        args = _splat_args(scene, True)
        ours = rasterize(*args, W, H)
        ref = rasterize_dense(*args, W, H)
        loss_ours = (ours[0] * scene["w_rgb"]).sum() + (ours[1] * scene["w_depth"]).sum()
        loss_ref = (ref[0] * scene["w_rgb"]).sum() + (ref[1] * scene["w_depth"]).sum()
        grads = zip(torch.autograd.grad(loss_ours, args[:5]), torch.autograd.grad(loss_ref, args[:5]))
        row["max_abs_err_rgb"] = float((ours[0] - ref[0]).detach().abs().max())
        row["max_rel_err_grad"] = max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-12)) for a, b in grads)

        def dense_forward():
            with torch.no_grad():
                return rasterize_dense(*_splat_args(scene, False), W, H)

        def dense_forward_backward():
            a = _splat_args(scene, True)
            out = rasterize_dense(*a, W, H)
            return torch.autograd.grad((out[0] * scene["w_rgb"]).sum() + (out[1] * scene["w_depth"]).sum(), a[:5])

        ref_reps = max(1, min(reps, 5))
        row["fwd_ms"] = time_call(lambda: ours_forward(scene), device, reps).median_ms
        row["fwd_bwd_ms"] = time_call(lambda: ours_forward_backward(scene), device, reps).median_ms
        row["dense_fwd_ms"] = time_call(dense_forward, device, ref_reps, warmup=1).median_ms
        row["dense_fwd_bwd_ms"] = time_call(dense_forward_backward, device, ref_reps, warmup=1).median_ms
    except Exception as exc:  # noqa: BLE001
        row["error"] = f"{type(exc).__name__}: {exc}"
        traceback.print_exc()
    return row


def _import_gsplat(device: torch.device) -> dict | None:
    """gsplat's ``rasterization`` when importable and the device is CUDA, with a status line either way."""
    if device.type != "cuda":
        return {"status": "not run (gsplat has no CPU rasterizer)", "rasterization": None}
    try:
        import gsplat

        return {"status": f"gsplat {gsplat.__version__}", "rasterization": gsplat.rasterization}
    except Exception as exc:  # noqa: BLE001 - optional comparison
        return {"status": f"not importable ({type(exc).__name__}: {exc})", "rasterization": None}


def _peak_memory(device: torch.device, scene: dict) -> dict:
    if device.type == "cuda":
        wdev = wp.get_device(str(device))
        warp_pool_before = wp.get_mempool_used_mem_high(wdev) if wp.is_mempool_enabled(wdev) else None
        peak = cuda_peak_bytes(lambda: ours_forward_backward(scene), device)
        result = {"peak_mib": peak / 2**20}
        if warp_pool_before is not None:
            result["warp_pool_high_mib"] = wp.get_mempool_used_mem_high(wdev) / 2**20
        return result
    return {"peak_mib": rss_peak_growth_bytes(lambda: ours_forward_backward(scene)) / 2**20}


def _print_row(row: dict) -> None:
    """Print a row as it is measured (the last CPU row of a workload stands for its rows)."""
    if "error" in row:
        print(f"  {row['workload']}: {row['error']}", flush=True)
    text = "  ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items() if k != "error")
    print(f"  {text}", flush=True)
