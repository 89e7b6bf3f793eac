"""``codecsplat bench codec``: encode and decode wall time of whole scenes, split into network, entropy coding
and bitstream packing/parsing, at the RE10K (2 x 256x256) and DL3DV (8 x 256x448) shapes.

Timing: warm-up runs first, then the median of ``--reps`` runs; each phase is bracketed by a device
synchronisation. Encode = MVEnc + FeatHead + R_pre + analysis + float64 prior path (network), range coding
(entropy, including moving the symbols to the host) and packing (bitstream, incl. the Deflate of the
cameras). Decode = parsing and CRCs (bitstream), range decoding interleaved with the prior path (entropy:
only the coder and the host transfers), and prior path, synthesis, depth head, R_post, GS head, 2D->3D
(network). The paper reports RE10K 0.062 s / 0.059 s and DL3DV 0.267 s / 0.273 s (encode / decode) on its GPU.

Without ``--checkpoint`` the model is randomly initialised (seeded, identical on every device); its
untrained posterior gives latents that round mostly to zero, so it is scaled by ``--posterior-gain`` to
code realistic symbol statistics (about 28 KiB per RE10K scene at lambda 128 with the default gain). On
CUDA every bitstream is also decoded by a CPU copy of the model and its symbols compared with the
encoder's (``cpu_bit_exact``). ``--write-bitstream DIR`` stores each shape's bitstream with a record of its
symbols; ``--decode-bitstream FILE`` decodes such a file on ``--device`` and checks that the symbols are
the recorded ones (bit-exactness across machines).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pathlib
import statistics

import torch

from ..cameras import Cameras
from ..errors import DataError, InputError
from ..measure import PhaseTimer, format_table, machine_name, no_timer, timed
from ..model.codecsplat import CodecSplat, model_id
from ..model.pretrained import load_pretrained
from ..nn.config import get_preset
from ..synthetic import make_rig
from .options import CODEC_SHAPES as SHAPES
from .options import CodecShape as Shape


LAMBDA = 128.0
"""Rate point of the timed runs (the coding time hardly depends on it)."""


def run(args: argparse.Namespace) -> dict:
    device = torch.device(args.device)
    if args.decode_bitstream:
        return _decode_recorded(pathlib.Path(args.decode_bitstream), args, device)
    reps = args.reps or (20 if device.type == "cuda" else 3)
    unknown = [s for s in args.shapes.split(",") if s not in SHAPES]
    if unknown:
        raise InputError(f"unknown shape {unknown[0]!r}; choose from {', '.join(SHAPES)}")
    rows = []
    for name in args.shapes.split(","):
        shape = SHAPES[name]
        model = build_model(shape, args, device)
        images, cameras = make_inputs(shape, args.seed, device)
        row = measure(model, images, cameras, reps)
        row.update(shape=name, views=shape.views, size=f"{shape.height}x{shape.width}", reps=reps,
                   paper_encode_s=shape.paper_encode_s, paper_decode_s=shape.paper_decode_s)
        encoded = model.encode_scene(images, cameras, LAMBDA)
        if device.type == "cuda" and not args.no_cpu_check:
            row["cpu_bit_exact"] = _symbols_equal(encoded.latents, _cpu_copy(model).decode_scene(encoded.data).latents)
        if args.write_bitstream:
            _write_recorded(pathlib.Path(args.write_bitstream), shape, args, encoded)
        rows.append(row)
        print(f"  {name:6s} encode {row['encode_s'] * 1e3:8.2f} ms  decode {row['decode_s'] * 1e3:8.2f} ms  "
              f"{row['bytes']} bytes", flush=True)
    table = format_table(rows, COLUMNS)
    print(f"\nscene codec at lambda {LAMBDA:g}, {machine_name(device)}\n{table}")
    return {"benchmark": "codec", "device": str(device), "machine": machine_name(device), "lambda": LAMBDA,
            "checkpoint": args.checkpoint, "rows": rows, "table": table}


COLUMNS = [
    ("shape", "shape", "s"),
    ("views", "views", "d"),
    ("size", "size", "s"),
    ("bytes", "bytes", "d"),
    ("encode_s", "encode s", ".4f"),
    ("encode_network_s", "enc network", ".4f"),
    ("encode_entropy_s", "enc entropy", ".4f"),
    ("encode_bitstream_s", "enc bitstream", ".4f"),
    ("decode_s", "decode s", ".4f"),
    ("decode_network_s", "dec network", ".4f"),
    ("decode_entropy_s", "dec entropy", ".4f"),
    ("decode_bitstream_s", "dec bitstream", ".4f"),
    ("paper_encode_s", "paper enc s", ".3f"),
    ("paper_decode_s", "paper dec s", ".3f"),
    ("cpu_bit_exact", "CUDA->CPU bit-exact", ""),
]


def build_model(shape: Shape, args: argparse.Namespace, device: torch.device) -> CodecSplat:
    """The pretrained model of ``--checkpoint``, or a seeded random one with its posterior scaled."""
    if args.checkpoint:
        return load_pretrained(args.checkpoint, device)
    torch.manual_seed(args.seed)
    model = CodecSplat(get_preset(shape.preset), codec=True).eval()
    model.codec.scale_posterior(args.posterior_gain)
    return model.to(device)


def make_inputs(shape: Shape, seed: int, device: torch.device) -> tuple[torch.Tensor, Cameras]:
    """Smooth random images [V,3,H,W] in [0,1] (upsampled noise, so they carry structure) and a camera rig."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(shape.views, 3, shape.height // 16, shape.width // 16, generator=g)
    images = torch.nn.functional.interpolate(coarse, size=(shape.height, shape.width), mode="bicubic").clamp(0, 1)
    cameras = make_rig(shape.views, shape.width, shape.height, dtype=torch.float32, seed=seed)
    return images.to(device), cameras.to(device)


def _timed(fn, device: torch.device) -> dict[str, float]:
    """{total, entropy, bitstream, network} seconds of one call ``fn(timer)``."""
    timer = PhaseTimer(device)
    _, total = timed(lambda: fn(timer), device)
    phases = {"entropy": timer.seconds.get("entropy", 0.0), "bitstream": timer.seconds.get("bitstream", 0.0)}
    return {"total": total, **phases, "network": total - sum(phases.values())}


def measure(model: CodecSplat, images: torch.Tensor, cameras: Cameras, reps: int, warmup: int = 2) -> dict:
    """Median encode and decode seconds (total and per phase) and the bitstream size."""
    device = images.device
    data = model.encode(images, cameras, LAMBDA)
    encode = lambda timer: model.encode_scene(images, cameras, LAMBDA, timer)  # noqa: E731
    decode = lambda timer: model.decode_scene(data, timer=timer)  # noqa: E731
    for _ in range(warmup):
        encode(no_timer)
        decode(no_timer)
    enc = [_timed(encode, device) for _ in range(reps)]
    dec = [_timed(decode, device) for _ in range(reps)]
    row = {"bytes": len(data), "model_id": model_id(model)}
    for name, runs in (("encode", enc), ("decode", dec)):
        row[f"{name}_s"] = statistics.median(r["total"] for r in runs)
        for phase in ("network", "entropy", "bitstream"):
            row[f"{name}_{phase}_s"] = statistics.median(r[phase] for r in runs)
    return row


def _cpu_copy(model: CodecSplat) -> CodecSplat:
    copy = CodecSplat(model.config, codec=True).eval()
    copy.load_state_dict({k: v.cpu() for k, v in model.state_dict().items()})
    return copy


def _symbols_equal(a: list[torch.Tensor], b: list[torch.Tensor]) -> bool:
    return len(a) == len(b) and all(torch.equal(x.cpu(), y.cpu()) for x, y in zip(a, b))


def _symbols_digest(latents: list[torch.Tensor]) -> str:
    sha = hashlib.sha256()
    for level in latents:
        sha.update(level.cpu().contiguous().numpy().astype("<i8").tobytes())
    return sha.hexdigest()


def _write_recorded(folder: pathlib.Path, shape: Shape, args: argparse.Namespace, encoded) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{shape.name}.csplat").write_bytes(encoded.data)
    record = {"shape": shape.name, "seed": args.seed, "posterior_gain": args.posterior_gain,
              "checkpoint": args.checkpoint, "symbols_sha256": _symbols_digest(encoded.latents),
              "encoded_on": machine_name(torch.device(args.device))}
    (folder / f"{shape.name}.latents.json").write_text(json.dumps(record, indent=1))


def _decode_recorded(file: pathlib.Path, args: argparse.Namespace, device: torch.device) -> dict:
    record_file = file.with_suffix(".latents.json")
    if not file.is_file() or not record_file.is_file():
        raise DataError(f"--decode-bitstream needs {file} and {record_file} (written by --write-bitstream)")
    record = json.loads(record_file.read_text())
    args.seed, args.posterior_gain, args.checkpoint = record["seed"], record["posterior_gain"], record["checkpoint"]
    model = build_model(SHAPES[record["shape"]], args, device)
    scene = model.decode_scene(file.read_bytes())
    exact = _symbols_digest(scene.latents) == record["symbols_sha256"]
    print(f"{file}: encoded on {record['encoded_on']}, decoded on {machine_name(device)}: "
          f"symbols {'bit-exact' if exact else 'DIFFER'}")
    return {"benchmark": "codec", "device": str(device), "machine": machine_name(device), "bitstream": str(file),
            "encoded_on": record["encoded_on"], "bit_exact": exact}
