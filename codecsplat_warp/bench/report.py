"""``codecsplat bench report``: error against median run time of every kernel and configuration (issue 8).

Kernels: ``unproject``, ``reproject_average``, ``plane_sweep_cost_volume`` and ``rasterize``, each timed
forward (no grad) and backward (the backward pass alone, on a retained graph), over configurations:

* dtype float32 or float64, on each device of ``--devices`` (CPU and CUDA);
* scene size (``--sizes``, see :data:`GEOMETRY_SIZES` and :data:`RASTER_SIZES`);
* ``plane_sweep_cost_volume``: the number of depth candidates;
* ``rasterize``: tile size, antialiasing mode and the early-stop transmittance ``min_transmittance`` (a pixel
  stops before the Gaussian that would take its transmittance to that value or below; 1e-4 by default).

Error is measured against a float64 reference of the same op on the same inputs: the plain-torch
reference (:mod:`codecsplat_warp.reference`, on the CPU) where it needs at most
:data:`DENSE_REFERENCE_LIMIT` elements, else the op's own float64 Warp kernels on the device (tied to the
torch reference by the tests); a float64 configuration without an affordable torch reference has no error.
Forward: max and RMS absolute error, relative L2 error, PSNR for images (rasterize RGB, peak 1), validity
flips of reprojections (samples valid in one precision and not the other, left out of the error as in
``bench geometry``). Backward: relative L2 error of the input gradients (largest over inputs). Run time:
median of repeated runs (:func:`codecsplat_warp.measure.time_call`).

Options that trade accuracy for time (:data:`TRADE_OFF_OPTIONS`: the early-stop transmittance) are measured
twice. The error (plotted, and compared on the Pareto front with the other rows of the kernel) is against
the float64 reference at the op's *default* setting, like every other row: it shows what a larger threshold
costs in accuracy (the PSNR column is then the PSNR against the default float64 render), and at threshold 0,
which composites further than the default, it is the default's own truncation. ``err_same_setting`` is the
relative L2 error against the float64 reference at the row's *own* setting: the kernel's arithmetic error,
which must stay as small as at the default (correctness).

The codec joins when :mod:`codecsplat_warp.codec` exists and a model loads (``--checkpoint``, else the
shipped default): for each lambda, distortion (MSE and PSNR of renders of held-out views against the
ground truth) against encode+decode time, and the zero-byte floor of copying the nearest context view
(:func:`measure_codec`).

``--out-dir`` receives ``report.json`` (rewritten after every row, so an interruption loses nothing
measured), ``report.md`` (tables per kernel, Pareto-optimal rows marked) and ``pareto.png`` (error against
time, log-log, one marker per kernel, the Pareto front of each kernel, phase and size filled and joined).
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import pathlib
import subprocess
import sys
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import torch

from ..errors import CodecSplatError, DataError, InputError
from ..eval.protocols import nearest_context_images
from ..export.files import atomic_output, write_json, write_text
from ..measure import format_table, machine_name, time_call
from ..ops.geometry import inverse_depth_candidates
from ..ops.raster import GAUSSIAN_ARGUMENTS
from ..synthetic import make_rig, smooth_depth
from .extreme import COST_VOLUME, RASTERIZE, REPROJECT, UNPROJECT, Op, Problem, device_arguments
from .extreme import forward_backward as _forward_backward
from .extreme import reference_arguments
from .geometry import SHAPES, Shape
from .options import REPORT_KERNELS as KERNELS
from .raster import Workload, make_scene

DENSE_REFERENCE_LIMIT = 20_000_000
"""Largest problem (elements the dense reference materialises) checked against the plain-torch reference."""

ERROR_FLOOR = 1e-18
"""Errors below this (e.g. exactly 0) are drawn at this value on the log-scale plot."""

TRADE_OFF_OPTIONS = ("min_transmittance",)
"""Op options that trade accuracy for time: their rows' error is against the reference at the op's default, and
``err_same_setting`` against the reference at the row's own value."""

RASTER_THRESHOLDS = (0.0, 1e-3, 1e-2)
"""Early-stop transmittances of the full report besides the default 1e-4 (float32, tile 16, classic)."""


# --------------------------------------------------------------------------------------------------
# Configurations
GEOMETRY_SIZES = {
    "tiny": Shape("tiny", 2, 8, 16, 16, 32, 32),
    "small": Shape("small", 2, 32, 32, 32, 64, 64),
    "re10k-64": SHAPES["re10k-64"],
    "dl3dv-64": SHAPES["dl3dv-64"],
}
"""Scene sizes of the geometry kernels (:class:`.geometry.Shape`: ``views`` cameras at ``image_h`` x ``image_w``,
``channels`` features on a ``grid_h`` x ``grid_w`` grid, which unprojection uses as its depth map); the RE10K/DL3DV
ones are those of ``bench geometry``."""

RASTER_SIZES = {
    "tiny": Workload("tiny", 1, 24, 24),
    "small": Workload("small", 1, 48, 48),
    "re10k": Workload("re10k", 2, 256, 256),
    "dl3dv": Workload("dl3dv", 8, 256, 448),
}
"""Scene sizes of the rasterizer: pixel-aligned Gaussians of ``views`` context views rendered into one
``height`` x ``width`` target (``bench raster``'s workloads; tiny has 576 Gaussians, small 2,304)."""



@dataclass(frozen=True)
class Entry:
    """One configuration of one kernel: ``options`` are the op's keyword arguments being varied."""

    kernel: str
    size: str
    dtype: torch.dtype
    options: tuple[tuple[str, object], ...] = ()

    @property
    def config(self) -> str:
        """Human-readable configuration, e.g. ``float32, tile_size=8, mode=antialiased``."""
        return ", ".join([_dtype_name(self.dtype)] + [f"{k}={v}" for k, v in self.options])


FLOATS = (torch.float32, torch.float64)


def entries(quick: bool, kernels: Sequence[str], sizes: Sequence[str] | None = None,
            dtypes: Sequence[torch.dtype] = FLOATS) -> list[Entry]:  # fmt: skip
    """The configurations to measure (``quick``: a small CPU-friendly set on the tiny sizes), keeping only
    the given ``sizes`` (None: all) and ``dtypes``."""
    return [entry for kernel in kernels for entry in (_quick_entries(kernel) if quick else _full_entries(kernel))
            if (sizes is None or entry.size in sizes) and entry.dtype in dtypes]  # fmt: skip


def _quick_entries(kernel: str) -> list[Entry]:
    if kernel == "plane_sweep_cost_volume":
        return [Entry(kernel, "tiny", torch.float32, (("candidates", 4),)),
                Entry(kernel, "tiny", torch.float32, (("candidates", 16),)),
                Entry(kernel, "tiny", torch.float64, (("candidates", 4),))]  # fmt: skip
    if kernel == "rasterize":
        variants = ((torch.float32, 16, "classic"), (torch.float64, 16, "classic"), (torch.float32, 8, "classic"),
                    (torch.float32, 16, "antialiased"))  # fmt: skip
        return [Entry(kernel, "tiny", dtype, (("tile_size", tile), ("mode", mode))) for dtype, tile, mode in variants]
    return [Entry(kernel, "tiny", dtype) for dtype in FLOATS]


def _full_entries(kernel: str) -> list[Entry]:
    if kernel == "rasterize":
        sizes = ("small", "re10k", "dl3dv")
        variants = [Entry(kernel, size, dtype, (("tile_size", tile), ("mode", mode)))
                    for size in sizes for dtype in FLOATS for tile in (8, 16, 32)
                    for mode in ("classic", "antialiased")]  # fmt: skip
        thresholds = [Entry(kernel, size, torch.float32, (("tile_size", 16), ("mode", "classic"),
                                                           ("min_transmittance", threshold)))
                      for size in sizes for threshold in RASTER_THRESHOLDS]  # fmt: skip
        return variants + thresholds
    sizes = ("small", "re10k-64", "dl3dv-64")
    if kernel == "plane_sweep_cost_volume":
        return [Entry(kernel, size, dtype, (("candidates", d),))
                for size in sizes for dtype in FLOATS for d in (8, 32, 64, 128)]  # fmt: skip
    return [Entry(kernel, size, dtype) for size in sizes for dtype in FLOATS]


# --------------------------------------------------------------------------------------------------
# Problems (float64 on the CPU, in the form of the extreme-cases catalog)
def geometry_problem(entry: Entry) -> Problem:
    """Inputs of a geometry kernel at ``entry.size``: smooth depths, random features, rig cameras."""
    size = GEOMETRY_SIZES[entry.size]
    cams = make_rig(size.views, size.image_w, size.image_h)
    depth = smooth_depth(size.views, size.grid_h, size.grid_w)
    if entry.kernel == "unproject":
        return Problem({"depth": depth}, ("depth",), {"cameras": cams})
    g = torch.Generator().manual_seed(3)
    feat = torch.randn(size.views, size.channels, size.grid_h, size.grid_w, generator=g, dtype=torch.float64)
    if entry.kernel == "reproject_average":
        return Problem({"feat": feat, "depth": depth}, ("feat", "depth"), {"cameras": cams})
    candidates = inverse_depth_candidates(cams, dict(entry.options)["candidates"])
    return Problem({"feat": feat, "candidates": candidates}, ("feat",), {"cameras": cams})


def raster_problem(entry: Entry) -> Problem:
    """``bench raster``'s pixel-aligned scene at ``entry.size``, with the entry's tile size and mode."""
    workload = RASTER_SIZES[entry.size]
    scene = make_scene(workload, torch.device("cpu"))
    inputs = {k: scene[k].double() for k in GAUSSIAN_ARGUMENTS}
    return Problem(inputs, GAUSSIAN_ARGUMENTS, {"viewmats": scene["viewmats"].double(), "Ks": scene["Ks"].double()},
                   {"width": scene["width"], "height": scene["height"], **dict(entry.options)})  # fmt: skip


@dataclass(frozen=True)
class KernelSpec:
    """How to build, run and check one kernel."""

    op: Op
    problem: Callable[[Entry], Problem]
    reference_elements: Callable[[Problem], int]
    """Elements the dense torch reference materialises for a problem (compared with DENSE_REFERENCE_LIMIT)."""
    image: bool = False
    """The first output is an image in [0, 1] (PSNR is reported)."""
    counts: bool = False
    """The second output counts valid samples (validity flips are reported, not mixed into the error)."""


def _views_sources_cells(p: Problem) -> int:
    feat = p.inputs["feat"]
    V, C, H, W = feat.shape
    return V * max(V - 1, 1) * C * H * W * p.inputs.get("candidates", feat.new_zeros(1, 1)).shape[1]


def _raster_cells(p: Problem) -> int:
    return p.constants["viewmats"].shape[0] * p.options["width"] * p.options["height"] * p.inputs["means"].shape[0]


SPECS = {
    "unproject": KernelSpec(UNPROJECT, geometry_problem, lambda p: p.inputs["depth"].numel() * 3),
    "reproject_average": KernelSpec(REPROJECT, geometry_problem, _views_sources_cells, counts=True),
    "plane_sweep_cost_volume": KernelSpec(COST_VOLUME, geometry_problem, _views_sources_cells),
    "rasterize": KernelSpec(RASTERIZE, raster_problem, _raster_cells, image=True),
}


# --------------------------------------------------------------------------------------------------
# Measurement
def measure(entry: Entry, device: torch.device, reps: int) -> list[dict]:
    """The forward and the backward row of one configuration on one device."""
    spec = SPECS[entry.kernel]
    problem = spec.problem(entry)
    args = device_arguments(problem, entry.dtype, device)
    default = at_default_setting(problem)
    reference, reference_name = _reference(spec, default, entry.dtype, device)
    out, grads, weights = _forward_backward(spec.op.run, args, problem.grad, reference[2] if reference else None)
    common = {"kernel": entry.kernel, "size": entry.size, "device": str(device), "dtype": _dtype_name(entry.dtype),
              "config": entry.config, "reps": reps, "reference": reference_name}  # fmt: skip
    forward = {**common, "phase": "forward", **_time(lambda: _no_grad(spec.op.run, args), device, reps)}
    backward = {**common, "phase": "backward", **_time(_backward_call(spec.op.run, args, problem.grad, weights),
                                                         device, reps)}  # fmt: skip
    if reference is not None:
        forward.update(forward_errors(out, reference[0], spec))
        backward.update(gradient_errors(grads, reference[1]))
    if default is not problem:
        same, _ = _reference(spec, problem, entry.dtype, device)
        if same is not None:
            forward["err_same_setting"] = forward_errors(out, same[0], spec)["error"]
            backward["err_same_setting"] = gradient_errors(grads, same[1])["error"]
    return [forward, backward]


def at_default_setting(problem: Problem) -> Problem:
    """``problem`` without its :data:`TRADE_OFF_OPTIONS` (the op's defaults apply), or ``problem`` itself."""
    options = {k: v for k, v in problem.options.items() if k not in TRADE_OFF_OPTIONS}
    return problem if len(options) == len(problem.options) else replace(problem, options=options)


def _reference(spec: KernelSpec, problem: Problem, dtype: torch.dtype, device: torch.device):
    """(outputs, gradients, weights) of the float64 reference and its name, or (None, why not)."""
    if spec.reference_elements(problem) <= DENSE_REFERENCE_LIMIT:
        args = reference_arguments(problem, dtype)
        return _forward_backward(spec.op.reference, args, problem.grad, None), "torch float64 (CPU)"
    if dtype == torch.float64:
        return None, "none (float64 is the reference; the torch one is too large)"
    rounded = replace(problem, inputs={k: v.to(dtype).to(torch.float64) for k, v in problem.inputs.items()})
    args = device_arguments(rounded, torch.float64, device)
    return _forward_backward(spec.op.run, args, problem.grad, None), "warp float64"


def _time(fn: Callable[[], object], device: torch.device, reps: int) -> dict:
    timing = time_call(fn, device, reps, warmup=1)
    return {"time_ms": timing.median_ms, "time_spread_ms": [timing.min_ms, timing.max_ms]}


def _no_grad(fn: Callable, args: dict):
    with torch.no_grad():
        return fn(**args)


def _backward_call(fn: Callable, args: dict, grad: tuple[str, ...], weights: list[torch.Tensor]) -> Callable:
    """A callable running only the backward pass of ``fn`` (its graph is built once and retained)."""
    leaves = {k: args[k].detach().requires_grad_() for k in grad}
    outputs = fn(**{**args, **leaves})
    loss = sum((o * w.to(device=o.device, dtype=o.dtype)).sum() for o, w in zip(outputs, weights))
    return lambda: torch.autograd.grad(loss, list(leaves.values()), retain_graph=True, allow_unused=True)


def forward_errors(outputs: Sequence[torch.Tensor], reference: Sequence[torch.Tensor], spec: KernelSpec) -> dict:
    """Errors of the first output (points, average, cost or RGB) against the reference.

    Returns ``err_max`` and ``err_rms`` (absolute), ``error`` (relative L2), ``psnr_db`` for images and
    ``validity_flips`` for reprojections (whose flipped samples are left out of the errors).
    """
    got, ref = outputs[0].detach().cpu().double(), reference[0].detach().cpu().double()
    result = {}
    keep = torch.ones_like(ref, dtype=torch.bool)
    if spec.counts:
        same = outputs[1].detach().cpu() == reference[1].detach().cpu()
        result["validity_flips"] = int((~same).sum())
        keep = same[:, None].expand_as(ref)
    diff = (got - ref)[keep]
    mse = float((diff**2).mean()) if diff.numel() else 0.0
    result.update(err_max=float(diff.abs().max()) if diff.numel() else 0.0, err_rms=math.sqrt(mse),
                  error=_relative_l2(diff, ref[keep]))  # fmt: skip
    if spec.image:
        result["psnr_db"] = math.inf if mse == 0 else -10.0 * math.log10(mse)
    return result


def gradient_errors(grads: Sequence[torch.Tensor], reference: Sequence[torch.Tensor]) -> dict:
    """``error``: the largest relative L2 error of the input gradients; ``err_max_rel``: the largest
    max-abs error relative to the gradient's largest magnitude."""
    rel_l2, rel_max = [], []
    for g, r in zip(grads, reference):
        diff = g.detach().cpu().double() - r.detach().cpu().double()
        rel_l2.append(_relative_l2(diff, r))
        rel_max.append(float(diff.abs().max() / r.abs().max().clamp_min(1e-300)) if r.numel() else 0.0)
    return {"error": max(rel_l2, default=0.0), "err_max_rel": max(rel_max, default=0.0)}


def _relative_l2(diff: torch.Tensor, ref: torch.Tensor) -> float:
    """||diff|| / ||ref|| (the absolute norm where the reference is zero)."""
    norm = float(ref.double().norm())
    return float(diff.double().norm()) / norm if norm > 0 else float(diff.double().norm())


def _dtype_name(dtype: torch.dtype) -> str:
    return str(dtype).replace("torch.", "")


# --------------------------------------------------------------------------------------------------
# Codec (PSNR against encode+decode time per lambda)
QUICK_LAMBDAS = (64.0, 512.0)
COPY_NEAREST_CONFIG = "copy nearest context view"
"""The codec table's zero-byte floor row (its ``config``)."""
FULL_LAMBDAS = (16.0, 32.0, 64.0, 128.0, 256.0, 512.0, 1024.0)


def codec_available() -> bool:
    """Whether the scene codec package exists in this installation (the hook's switch)."""
    return importlib.util.find_spec("codecsplat_warp.codec") is not None


def measure_codec(model, context: tuple[torch.Tensor, object], targets: tuple[torch.Tensor, object],
                  lams: Sequence[float], device: torch.device, reps: int, scene: str) -> list[dict]:  # fmt: skip
    """The floor, then one row per lambda: encode+decode median time, bytes, distortion of the rendered targets.

    The floor (:data:`COPY_NEAREST_CONFIG`, Table 1's "copy the nearest context view" row) predicts each target
    by the context image whose camera centre is nearest, at zero bytes; it has no run time (``time_ms``
    absent), so it sits on no Pareto front and out of the time plot. Uses the codec contract
    ``model.encode(images, cameras, lam) -> bytes`` and ``model.decode(data, device) -> Gaussians``, and
    ``model.render(gaussians, cameras)["rgb"]`` for the held-out views.

    Args:
        model: a :class:`~codecsplat_warp.model.CodecSplat` with its codec, on ``device``.
        context: (images float32 [V,3,H,W] in [0,1], Cameras) coded into the bitstream.
        targets: (images float32 [T,3,H,W] in [0,1], Cameras) rendered from the decoded Gaussians and compared.
        scene: name of the scene (the row's size).
    """
    from ..metrics.image import psnr

    images, cameras = context
    target_images, target_cameras = targets
    dtype = _dtype_name(next(model.parameters()).dtype)

    def row(config: str, size: int, value: float) -> dict:
        return {"kernel": "codec", "phase": "encode+decode", "size": scene, "device": str(device), "dtype": dtype,
                "config": config, "bytes": size, "psnr_db": value, "error": 10.0 ** (-value / 10.0),
                "reference": "ground-truth images"}

    nearest = nearest_context_images(images, cameras, target_cameras)
    rows = [row(COPY_NEAREST_CONFIG, 0, float(psnr(nearest, target_images).mean()))]
    for lam in lams:
        data = model.encode(images, cameras, lam)
        rendered = model.render(model.decode(data, device), target_cameras)["rgb"]
        timing = time_call(lambda lam=lam: model.decode(model.encode(images, cameras, lam), device), device, reps,
                           warmup=1)  # fmt: skip
        rows.append({**row(f"lambda={lam:g}", len(data), float(psnr(rendered, target_images).mean())), "lam": lam,
                     "reps": reps, "time_ms": timing.median_ms, "time_spread_ms": [timing.min_ms, timing.max_ms]})
    return rows


def codec_rows(checkpoint: str | None, device: torch.device, lams: Sequence[float],
               reps: int) -> tuple[list[dict], str]:  # fmt: skip
    """Codec rows on a procedural scene at the model's size, or no rows and the reason."""
    if not codec_available():
        return [], "skipped: codecsplat_warp.codec is not installed"
    from ..model.pretrained import load_pretrained

    try:
        model = load_pretrained(checkpoint, device)
    except DataError as exc:
        return [], f"skipped: no codec model ({exc})"
    context, targets, name = codec_scene(model.config, device)
    return measure_codec(model, context, targets, lams, device, reps, name), f"measured on {name}"


def codec_scene(config, device: torch.device, seed: int = 0):
    """A procedural scene at the model's size: ``config.num_views`` context views and two held-out views
    between them. Returns ((images, cameras), (target images, target cameras), name)."""
    from ..data.procedural import ProceduralConfig, procedural_scene

    total = config.num_views + 2
    scene = procedural_scene(seed, ProceduralConfig(width=config.width, height=config.height, num_views=total))
    images = scene.images.to(device=device, dtype=torch.float32) / 255.0
    cameras = scene.cameras.to(device=device)
    held_out = [1, total - 2]
    context = [v for v in range(total) if v not in held_out]
    return ((images[context], cameras.select(context)), (images[held_out], cameras.select(held_out)),
            f"{scene.key} ({config.num_views}+2 views, {config.width}x{config.height})")  # fmt: skip


# --------------------------------------------------------------------------------------------------
# Pareto fronts
def pareto_front(points: Sequence[tuple[float, float]]) -> list[bool]:
    """For (time, error) points, True where no other point is at least as good in both and better in one."""
    return [
        not any(t2 <= t and e2 <= e and (t2 < t or e2 < e) for j, (t2, e2) in enumerate(points) if j != i)
        for i, (t, e) in enumerate(points)
    ]


def group_key(row: dict) -> tuple[str, str, str]:
    """Rows compete on a Pareto front within one kernel, phase and scene size (across dtypes, devices and
    the kernel's options)."""
    return row["kernel"], row["phase"], row["size"]


def mark_pareto(rows: list[dict]) -> None:
    """Set ``row["pareto"]`` on every row with an error (None where there is no error to compare)."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        row["pareto"] = None
        if row.get("error") is not None and row.get("time_ms") is not None:
            groups.setdefault(group_key(row), []).append(row)
    for members in groups.values():
        for row, on_front in zip(members, pareto_front([(r["time_ms"], r["error"]) for r in members])):
            row["pareto"] = on_front


# --------------------------------------------------------------------------------------------------
# Outputs
COLUMNS = [
    ("phase", "phase", "s"), ("size", "size", "s"), ("device", "device", "s"), ("config", "configuration", "s"),
    ("time_ms", "median ms", ".3f"), ("error", "rel. error", ".2e"), ("err_same_setting", "own-setting err", ".2e"),
    ("err_max", "max abs err", ".2e"),
    ("err_rms", "RMS err", ".2e"), ("err_max_rel", "max rel err", ".2e"), ("psnr_db", "PSNR dB", ".1f"),
    ("validity_flips", "flips", "d"), ("bytes", "bytes", ",d"), ("front", "Pareto", "s"), ("failed", "failed", "s"),
]  # fmt: skip


ERROR_LEGEND = (
    "Error (rel. error, the plotted one): forward = relative L2 error of the output against the float64 reference, "
    "with its max and RMS absolute error (images also PSNR, peak 1); backward = largest relative L2 error of the "
    "input gradients, with the largest max-abs error relative to the gradient's magnitude; codec = MSE of the "
    "rendered held-out views against the ground truth, beside the zero-byte floor of copying the nearest context view "
    "(no run time, so on no front). Pareto: optimal within its kernel, phase and size (★). "
    "Rasterizer errors include per-pixel threshold flips: a row whose alpha lies within rounding of 1/255 (or a "
    "transmittance within rounding of the early stop) is used in one precision and skipped in the other, a jump of "
    "up to ~4e-3 at that pixel (like the validity flips of reprojections, but not separable from the image error). "
    "Rows with an early-stop transmittance (min_transmittance) are measured against the float64 render at the "
    "default 1e-4, so their error and PSNR show what stopping earlier costs (at 0, which composites further than "
    "the default, the error is the default's truncation); own-setting err is the relative error against the "
    "float64 render at the row's own threshold (the kernel's arithmetic error)."
)


def markdown(result: dict) -> str:
    """The report as Markdown: header (machines, commit), one table per kernel."""
    lines = ["# Error against run time", ""]
    for device, machine in result["machines"].items():
        lines.append(f"- `{device}`: {machine}")
    lines += [f"- commit: `{result['commit']}`", f"- mode: {'quick' if result['quick'] else 'full'}",
              f"- codec: {result['codec']}", "",
              ERROR_LEGEND, ""]  # fmt: skip
    for kernel in [*KERNELS, "codec"]:
        rows = [r for r in result["rows"] if r["kernel"] == kernel]
        if not rows:
            continue
        rows = sorted(rows, key=lambda r: (r["phase"], r["size"], r.get("time_ms", math.inf)))
        shown = [{**r, "front": {True: "★", False: "", None: "n/a"}[r.get("pareto")]} for r in rows]
        lines += [f"## {kernel}", "", format_table(shown, COLUMNS), ""]
    return "\n".join(lines) + "\n"


MARKERS = {"unproject": "o", "reproject_average": "s", "plane_sweep_cost_volume": "^", "rasterize": "D", "codec": "*"}
PHASE_COLORS = {"forward": "C0", "backward": "C1", "encode+decode": "C3"}


def plot_pareto(rows: list[dict], path: pathlib.Path, title: str) -> None:
    """Error against median time, log-log: one marker per kernel, one colour per phase; the Pareto-optimal
    points of each (kernel, phase, size) filled and joined by a step line, the dominated ones hollow."""
    try:
        import matplotlib
    except ImportError as exc:
        raise CodecSplatError("the Pareto plot needs matplotlib (bench extra): pip install -e '.[bench]'") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    fig, ax = plt.subplots(figsize=(8.5, 6.0))
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        if row.get("pareto") is not None:
            groups.setdefault(group_key(row), []).append(row)
    for (kernel, phase, _), members in groups.items():
        color, marker = PHASE_COLORS[phase], MARKERS[kernel]
        for row in members:
            face = color if row["pareto"] else "none"
            ax.plot(row["time_ms"], max(row["error"], ERROR_FLOOR), marker, color=color, markerfacecolor=face,
                    markersize=7, alpha=0.9)  # fmt: skip
            if row["pareto"]:
                ax.annotate(_short_config(row), (row["time_ms"], max(row["error"], ERROR_FLOOR)), fontsize=5.5,
                            textcoords="offset points", xytext=(4, 3), color=color)  # fmt: skip
        front = sorted((r["time_ms"], max(r["error"], ERROR_FLOOR)) for r in members if r["pareto"])
        if len(front) > 1:
            ax.step(*zip(*front), where="post", color=color, linewidth=1.0, alpha=0.6)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("median run time (ms)")
    ax.set_ylabel(f"error against float64 (relative L2; codec: MSE); floor {ERROR_FLOOR:g}")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    present = {r["kernel"] for r in rows if r.get("pareto") is not None}
    phases = {r["phase"] for r in rows if r.get("pareto") is not None}
    handles = [Line2D([], [], linestyle="", marker=MARKERS[k], color="0.3", label=k) for k in MARKERS if k in present]
    handles += [Line2D([], [], linestyle="", marker="o", color=PHASE_COLORS[p], label=p) for p in PHASE_COLORS
                if p in phases]  # fmt: skip
    handles.append(Line2D([], [], linestyle="", marker="o", color="0.3", markerfacecolor="none", label="dominated"))
    ax.legend(handles=handles, fontsize=8, loc="best")
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=130)
    plt.close(fig)


def _short_config(row: dict) -> str:
    """Plot label of a row: device and configuration in short form (``cuda f32 tile 8 classic stop 0.01``)."""
    text = f"{row['device']} {row['config']}".replace("float32", "f32").replace("float64", "f64")
    text = text.replace(", ", " ").replace("mode=", "").replace("candidates=", "D=").replace("tile_size=", "tile ")
    return text.replace("min_transmittance=", "stop ")


def _commit() -> str:
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty"], capture_output=True, text=True, timeout=10,
                             cwd=pathlib.Path(__file__).resolve().parent)  # fmt: skip
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


# --------------------------------------------------------------------------------------------------
# Command
def run(args: argparse.Namespace) -> dict:
    from tqdm import tqdm

    devices = _devices(args)
    kernels = _choices(args.kernels, KERNELS, "kernel")
    sizes = None if args.sizes is None else _choices(args.sizes, (*GEOMETRY_SIZES, *RASTER_SIZES), "size")
    dtypes = [getattr(torch, name) for name in _choices(args.dtypes, [_dtype_name(t) for t in FLOATS], "dtype")]
    jobs = [(e, d) for d in devices for e in entries(args.quick, kernels, sizes, dtypes)]
    out_dir = pathlib.Path(args.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    result = {"benchmark": "report", "quick": bool(args.quick), "commit": _commit(),
              "machines": {str(d): machine_name(d) for d in devices}, "rows": [],
              "codec": "not run yet"}  # fmt: skip
    for entry, device in tqdm(jobs, desc="bench report", disable=getattr(args, "json", False)):
        reps = _reps(args, device)
        try:
            result["rows"] += measure(entry, device, reps)
        except Exception as exc:  # noqa: BLE001 - a configuration that fails is a row, not a lost report
            result["rows"].append({"kernel": entry.kernel, "phase": "forward", "size": entry.size,
                                   "device": str(device), "dtype": _dtype_name(entry.dtype), "config": entry.config,
                                   "failed": f"{type(exc).__name__}: {exc}"[:300]})  # fmt: skip
        write_json(out_dir / "report.json", result)
    result["codec"] = "skipped (--no-codec)"
    if not args.no_codec:
        codec, result["codec"] = codec_rows(args.checkpoint, devices[-1], QUICK_LAMBDAS if args.quick
                                            else FULL_LAMBDAS, _reps(args, devices[-1]))  # fmt: skip
        result["rows"] += codec
    return finish(result, out_dir, quiet=getattr(args, "json", False))


def finish(result: dict, out_dir: pathlib.Path, quiet: bool = False) -> dict:
    """Mark the Pareto fronts, write report.json, report.md and pareto.png into ``out_dir`` and print the
    Markdown (on stderr when ``quiet``: stdout then carries the caller's JSON)."""
    mark_pareto(result["rows"])
    paths = {name: str(out_dir / name) for name in ("report.json", "report.md", "pareto.png")}
    result["files"] = paths
    write_text(paths["report.md"], markdown(result))
    plot_pareto(result["rows"], pathlib.Path(paths["pareto.png"]),
                "error vs median run time - " + "; ".join(f"{d}: {m}" for d, m in result["machines"].items()))
    write_json(paths["report.json"], result)
    print(f"\n{markdown(result)}\nwrote {', '.join(paths.values())}", file=sys.stderr if quiet else sys.stdout)
    return result


def _devices(args: argparse.Namespace) -> list[torch.device]:
    from ..device import resolve_device

    names = args.devices.split(",") if args.devices else [args.device]
    return [resolve_device(n) for n in names]


def _choices(text: str, allowed: Sequence[str], what: str) -> list[str]:
    chosen = [t for t in text.split(",") if t]
    unknown = [t for t in chosen if t not in allowed]
    if unknown or not chosen:
        raise InputError(f"unknown {what} {unknown[0] if unknown else text!r}; choose from {', '.join(allowed)}")
    return chosen


def _reps(args: argparse.Namespace, device: torch.device) -> int:
    if args.reps:
        return args.reps
    if args.quick:
        return 3
    return 20 if device.type == "cuda" else 5

