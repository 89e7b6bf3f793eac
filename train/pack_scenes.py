"""Pack real scenes small enough to carry to a training machine: JPEGs resized so that their shorter side is
``--short-side`` pixels, ``cameras.json`` with intrinsics scaled to match (everything else unchanged).

    python -m train.pack_scenes ../shared/data/scenes .device/a/scenes --short-side 256

The packed folder is a valid scene directory for ``train.stage1 --data`` (each scene keeps the
``codecsplat-scene-v1`` format); training resizes and centre-crops it to the preset size as usual.
"""

from __future__ import annotations

import argparse
import json
import pathlib

from PIL import Image
from tqdm import tqdm

from codecsplat_warp.errors import DataError

def pack_scene(source: pathlib.Path, target: pathlib.Path, short_side: int, quality: int = 85) -> int:
    """Pack one scene folder (with ``cameras.json``); returns the bytes written."""
    description = json.loads((source / "cameras.json").read_text())
    frames = description.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{source / 'cameras.json'}: no frames")
    written = 0
    for frame in frames:
        scale = min(1.0, short_side / min(frame["w"], frame["h"]))
        width, height = round(frame["w"] * scale), round(frame["h"] * scale)
        sx, sy = width / frame["w"], height / frame["h"]
        image_path = target / frame["file"]
        image_path.parent.mkdir(parents=True, exist_ok=True)
        with Image.open(source / frame["file"]) as image:
            image.convert("RGB").resize((width, height), Image.Resampling.LANCZOS).save(image_path, quality=quality)
        written += image_path.stat().st_size
        frame.update(w=width, h=height, fx=frame["fx"] * sx, cx=frame["cx"] * sx, fy=frame["fy"] * sy, cy=frame["cy"] * sy)
    (target / "cameras.json").write_text(json.dumps(description))
    return written + (target / "cameras.json").stat().st_size


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m train.pack_scenes``."""
    parser = argparse.ArgumentParser(prog="python -m train.pack_scenes", description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=pathlib.Path, help="folder of scene folders (each with cameras.json)")
    parser.add_argument("target", type=pathlib.Path, help="folder to write the packed scene folders to")
    parser.add_argument("--short-side", type=int, default=256,
                        help="shorter image side after packing, pixels (default %(default)s)")
    parser.add_argument("--quality", type=int, default=85, help="JPEG quality, 1-95 (default %(default)s)")
    parser.add_argument("--scenes", default="", help="comma-separated scene names (default: all)")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    names = [n for n in args.scenes.split(",") if n] or sorted(p.parent.name for p in args.source.glob("*/cameras.json"))
    if not names:
        raise SystemExit(f"no scenes (*/cameras.json) under {args.source}")
    total = 0
    for name in tqdm(names, desc="pack"):
        total += pack_scene(args.source / name, args.target / name, args.short_side, args.quality)
    print(f"packed {len(names)} scenes, {total / 2**20:.1f} MiB -> {args.target}")


if __name__ == "__main__":
    main()
