"""``codecsplat bench crossdevice``: a bitstream decodes to the same scene on every device, across machines.

``--write DIR`` (on the machine that encodes, normally with ``--device cuda``): encodes a procedural room (the
demo's kind of scene, at the shipped model's size and view count) with the shipped model, decodes it there in
float32 and with the bf16 opt-in (``decode_scene(..., precision="bfloat16")``), times both decodes in interleaved
rounds, and writes the fixture, under 1 MB:

* ``scene.csplat``: the bitstream;
* ``gaussians.npz``: the float32 decode's Gaussians at :data:`SAMPLE` fixed indices (and the indices);
* ``renders.npz``: the float32 decode rendered into the context views at :data:`RENDER_SIZE`, float16, with the
  cameras;
* ``record.json``: device, machine, versions, model id, lambda, both decode times, and how far the bf16 decode
  moves the Gaussians and the renders from the float32 decode.

``--check DIR`` (any device, normally ``--device cpu`` on another machine): decodes the fixture's bitstream here in
float32 and compares it with the fixture: every Gaussian field within :data:`GAUSSIAN_TOLERANCE` of the
fixture's (max |difference| over max |value|, per field) and every render at or above :data:`RENDER_PSNR_DB`.
The exit code is 1 when it fails.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform

import numpy as np
import torch
import warp as wp

from ..cameras import Cameras
from ..data.procedural import ProceduralConfig, procedural_scene
from ..errors import DataError, InputError
from ..export.files import atomic_output, write_bytes, write_json
from ..gaussians import Gaussians
from ..measure import format_table, interleaved_medians, machine_name
from ..metrics.image import psnr
from ..model.codecsplat import model_id
from ..model.pretrained import load_pretrained

SAMPLE = 1024
"""Gaussians of the decode kept in the fixture (fixed random indices): all of them would be tens of MB."""

RENDER_SIZE = (128, 128)
"""(width, height) of the fixture's renders of the context views."""

GAUSSIAN_TOLERANCE = 1e-4
"""Largest accepted max |difference| / max |value| of a Gaussian field between two devices' float32 decodes."""

RENDER_PSNR_DB = 45.0
"""Smallest accepted PSNR between two devices' renders of their float32 decodes."""

SCENE_SEED = 3
LAMBDA = 1024.0
"""The fixture's scene seed and rate trade-off (the largest lambda: the most latents to get right)."""

FIELDS = ("means", "quats", "scales", "opacities", "sh")


def run(args: argparse.Namespace) -> dict:
    if bool(args.write) == bool(args.check):
        raise InputError("give exactly one of --write DIR and --check DIR")
    device = torch.device(args.device)
    result = write_fixture(pathlib.Path(args.write), device, args.reps) if args.write else \
        check_fixture(pathlib.Path(args.check), device)  # fmt: skip
    print(result["table"])
    return result


def write_fixture(folder: pathlib.Path, device: torch.device, reps: int | None = None) -> dict:
    """Encode, decode (float32 and bf16, timed) and write the fixture into ``folder`` (see the module docstring);
    returns the record, with its ``table``."""
    model = load_pretrained(None, device)
    images, cameras = _scene(model.config, device)
    data = model.encode(images, cameras, LAMBDA)
    decodes = {precision: (lambda p=precision: model.decode_scene(data, precision=p)) for precision in
               ("float32", "bfloat16")}  # fmt: skip
    times = interleaved_medians(decodes, device, reps or (20 if device.type == "cuda" else 3))
    exact, low = (decodes[p]() for p in ("float32", "bfloat16"))
    views = _render_cameras(exact.cameras)
    renders, low_renders = (_renders(model, scene.gaussians, views) for scene in (exact, low))
    record = {
        "device": str(device), "machine": machine_name(device), "python": platform.python_version(),
        "torch": torch.__version__, "warp": wp.config.version, "model_id": model_id(model), "lambda": LAMBDA,
        "seed": SCENE_SEED, "bitstream_bytes": len(data), "gaussians": len(exact.gaussians), "sample": SAMPLE,
        "render_size": list(RENDER_SIZE), "decode_ms": {"float32": times["float32"], "bfloat16": times["bfloat16"]},
        "bfloat16_against_float32": {
            "max_mean_shift": float((low.gaussians.means - exact.gaussians.means).abs().max()),
            "relative_error": _relative_errors(low.gaussians, exact.gaussians),
            "render_psnr_db": psnr(low_renders, renders, clip=False).tolist(),
        },
    }  # fmt: skip
    indices = _sample_indices(len(exact.gaussians))
    folder.mkdir(parents=True, exist_ok=True)
    write_bytes(folder / "scene.csplat", data)
    _write_npz(folder / "gaussians.npz", indices=indices.numpy(),
               **{name: getattr(exact.gaussians, name)[indices.to(device)].cpu().numpy() for name in FIELDS})
    _write_npz(folder / "renders.npz", rgb=renders.cpu().numpy().astype(np.float16),
               **{name: getattr(views, name).cpu().numpy() for name in ("K", "w2c", "near", "far")})
    write_json(folder / "record.json", record)
    rows = [{"precision": p, "decode_ms": times[p]} for p in ("float32", "bfloat16")]
    shift = record["bfloat16_against_float32"]
    record["table"] = (f"fixture written to {folder} on {record['machine']} ({len(data):,d} B bitstream)\n"
                       f"{format_table(rows, [('precision', 'decode', 's'), ('decode_ms', 'ms', '.1f')])}\n"
                       f"bf16 against float32: means moved up to {shift['max_mean_shift']:.3g}, renders at "
                       f"{min(shift['render_psnr_db']):.1f} dB")  # fmt: skip
    return record


def check_fixture(folder: pathlib.Path, device: torch.device) -> dict:
    """Decode the fixture's bitstream on ``device`` (float32) and compare it with the fixture: ``{"passed",
    "relative_error": {field: value}, "render_psnr_db": [per view], "fixture": the record, "table"}``.

    Raises:
        DataError: the folder is not a complete fixture.
        BitstreamError: the shipped model is not the one that wrote the fixture.
    """
    try:
        record = json.loads((folder / "record.json").read_text())
        data = (folder / "scene.csplat").read_bytes()
        stored = np.load(folder / "gaussians.npz")
        stored_renders = np.load(folder / "renders.npz")
    except (OSError, ValueError) as exc:
        raise DataError(f"{folder} is not a crossdevice fixture (write one with --write): {exc}") from None
    model = load_pretrained(None, device)
    decoded = model.decode_scene(data)
    indices = torch.from_numpy(stored["indices"]).to(device)
    mine = Gaussians(*(getattr(decoded.gaussians, name)[indices] for name in FIELDS))
    theirs = Gaussians(*(torch.from_numpy(stored[name]).to(device) for name in FIELDS))
    views = Cameras(*(torch.from_numpy(stored_renders[name]).to(device) for name in ("K", "w2c", "near", "far")),
                    *RENDER_SIZE)  # fmt: skip
    renders = _renders(model, decoded.gaussians, views)
    expected = torch.from_numpy(stored_renders["rgb"].astype(np.float32)).to(device)
    errors = _relative_errors(mine, theirs)
    psnr_db = psnr(renders, expected, clip=False).tolist()
    passed = max(errors.values()) <= GAUSSIAN_TOLERANCE and min(psnr_db) >= RENDER_PSNR_DB
    rows = [{"field": name, "error": value} for name, value in errors.items()]
    table = (f"{folder} (written on {record['device']}, {record['machine']}) decoded on {device}\n"
             f"{format_table(rows, [('field', 'Gaussians', 's'), ('error', 'max abs diff / max abs value', '.2e')])}\n"
             f"renders: {', '.join(f'{v:.1f}' for v in psnr_db)} dB PSNR\n"
             f"{'passed' if passed else 'FAILED'} (Gaussians within {GAUSSIAN_TOLERANCE:g}, renders >= "
             f"{RENDER_PSNR_DB:g} dB)")  # fmt: skip
    return {"passed": passed, "relative_error": errors, "render_psnr_db": psnr_db, "fixture": record,
            "table": table}


def _scene(config, device: torch.device) -> tuple[torch.Tensor, Cameras]:
    """The context images [V,3,H,W] in [0, 1] and cameras of a procedural room at the model's size."""
    scene = procedural_scene(SCENE_SEED, ProceduralConfig(width=config.width, height=config.height,
                                                          num_views=config.num_views, layout="room",
                                                          trajectory="forward"))  # fmt: skip
    return (scene.images.float() / 255.0).to(device), scene.cameras.to(device, torch.float32)


def _render_cameras(context: Cameras) -> Cameras:
    return context.to(dtype=torch.float32).rescaled(*RENDER_SIZE)


def _renders(model, gaussians: Gaussians, cameras: Cameras) -> torch.Tensor:
    with torch.no_grad():
        return model.render(gaussians, cameras)["rgb"].float()


def _write_npz(path: pathlib.Path, **arrays: np.ndarray) -> None:
    with atomic_output(path) as tmp, open(tmp, "wb") as file:
        np.savez_compressed(file, **arrays)


def _sample_indices(count: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(0)
    return torch.randperm(count, generator=generator)[: min(SAMPLE, count)].sort().values


def _relative_errors(got: Gaussians, reference: Gaussians) -> dict[str, float]:
    """max |got - reference| / max |reference| per field."""
    errors = {}
    for name in FIELDS:
        a, b = getattr(got, name).double(), getattr(reference, name).double()
        errors[name] = float((a - b).abs().max() / b.abs().max().clamp_min(1e-30))
    return errors
