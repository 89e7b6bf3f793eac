"""Write a stage-2 run's newest checkpoint as a pretrained model file (what ``load_pretrained`` reads).

    python -m train.export runs/stage2 codecsplat_warp/assets/codecsplat-default.safetensors --half

``--half`` rounds every weight to float16 first (half the file; the shipped default is stored so, within the
16 MB a file may have). The frozen mono prior's weights go into the file with the rest, so a user needs no
other file. The weights are the run's weight average where the checkpoint keeps one (``--ema-decay``), else the
raw ones (:func:`train.checkpoint.weights_for_use`). Prints the model id the bitstreams of the file will carry.
"""

from __future__ import annotations

import argparse
import pathlib

from codecsplat_warp.errors import InputError
from codecsplat_warp.model.codecsplat import model_id
from codecsplat_warp.model.pretrained import round_to_half, save_pretrained

from .validate import load_run


def export(run, path, half: bool) -> str:
    """Save the run's model at ``path``; returns its model id. InputError if the run has no codec (stage 1)."""
    model, step = load_run(pathlib.Path(run), device="cpu")
    if not model.has_codec:
        raise InputError(f"{run} is a stage-1 run (no codec): export a stage-2 run")
    if half:
        round_to_half(model)
    save_pretrained(model, path, half=half)
    return model_id(model)


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m train.export``."""
    parser = argparse.ArgumentParser(prog="python -m train.export", description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=pathlib.Path, help="stage-2 run folder (its weight average is exported)")
    parser.add_argument("path", type=pathlib.Path, help="model file to write (.safetensors)")
    parser.add_argument("--half", action="store_true",
                        help="store float16 weights, half the file size (default off: float32)")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    identifier = export(args.run, args.path, args.half)
    print(f"wrote {args.path} ({args.path.stat().st_size / 2**20:.2f} MiB), model id {identifier}")


if __name__ == "__main__":
    main()
