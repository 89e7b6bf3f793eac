"""The fixed held-out set of the quality work: scenes no training run may see, and their evaluation indices.

Ten real scenes of ``../shared/data/scenes`` (layouts from its README), chosen once and kept:

* forward-facing: llff_horns, cap_room_real (indoor);
* inward: dtu_scan37, nerd_mary_rose, bmvs_stone_horse, cap_fox;
* outward or walk-through: cap_rooftop, cap_lab_room (indoor), other_7scenes_redkitchen (indoor);
* driving: other_kitti06.

None of them was in the training set of the model shipped before this set was fixed (that model held out
llff_horns, dtu_scan37, cap_rooftop and nerd_mary_rose and trained on the other 18 of the first 22 scenes;
the rest of this set came with the 35 scenes added later). Their photographs are never procedural textures.

``heldout_index/index-re10k.json`` (2 context views, 3 targets) and ``index-dl3dv.json`` (8 context views, 3 targets) fix
each scene's frames in the pixelSplat index form, for ``codecsplat eval --index`` and ``train.validate``;
:func:`write_indices` made them (``python -m train.heldout DATA``), around each scene's middle view.

Beside them, ten *seen* scenes (:data:`SEEN`: training scenes of the same kinds, chosen the same way) with their
indices ``heldout_index/seen-re10k.json`` and ``seen-dl3dv.json``: a run's gain there against its gain on the held-out
set tells a generalisation gap (a gain on seen scenes alone) from a limit of the training itself (the same gain on
both).
"""

from __future__ import annotations

import argparse
import json
import pathlib

from codecsplat_warp.data import load_scene, split_context_targets

HELD_OUT = ("llff_horns", "cap_room_real", "dtu_scan37", "nerd_mary_rose", "bmvs_stone_horse", "cap_fox",
            "cap_rooftop", "cap_lab_room", "other_7scenes_redkitchen", "other_kitti06")
"""The held-out scene folders."""

SEEN = ("llff_fortress", "cap_office_desk", "dtu_scan65", "nerd_duck_queen", "bmvs_dinosaur", "cap_kangaroo",
        "cap_drone_town", "cap_bedroom_walk", "cap_south_building", "other_kitti01")
"""Training scenes scored as the held-out ones are (one of each held-out scene's kind: forward-facing, inward,
outward or walk-through, driving): the fit that training reaches on scenes it saw."""

FOLDER = pathlib.Path(__file__).resolve().parent / "heldout_index"
INDEX_FILES = {"re10k": FOLDER / "index-re10k.json", "dl3dv": FOLDER / "index-dl3dv.json"}
"""Evaluation index of each protocol."""
SEEN_INDEX_FILES = {"re10k": FOLDER / "seen-re10k.json", "dl3dv": FOLDER / "seen-dl3dv.json"}
"""Evaluation index of each protocol on the :data:`SEEN` scenes."""

CONTEXT_VIEWS = {"re10k": 2, "dl3dv": 8}
TARGET_VIEWS = 3


def selections(data_root, scenes=HELD_OUT) -> dict[str, dict[str, dict[str, list[int]]]]:
    """{protocol: {scene: {"context": [...], "target": [...]}}}: the views nearest each of ``scenes``'
    middle view, split by :func:`split_context_targets`."""
    out: dict[str, dict] = {protocol: {} for protocol in CONTEXT_VIEWS}
    for name in scenes:
        cameras = load_scene(pathlib.Path(data_root) / name).cameras
        for protocol, views in CONTEXT_VIEWS.items():
            context, target = split_context_targets(cameras, cameras.num_views // 2, views, TARGET_VIEWS)
            out[protocol][name] = {"context": context, "target": target}
    return out


def write_indices(data_root) -> None:
    """(Re)write :data:`INDEX_FILES` and :data:`SEEN_INDEX_FILES` from the scenes under ``data_root``."""
    for scenes, files in ((HELD_OUT, INDEX_FILES), (SEEN, SEEN_INDEX_FILES)):
        for protocol, entries in selections(data_root, scenes).items():
            lines = [f" {json.dumps(name)}: {json.dumps(entry)}" for name, entry in entries.items()]
            files[protocol].write_text("{\n" + ",\n".join(lines) + "\n}\n")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m train.heldout``."""
    parser = argparse.ArgumentParser(prog="python -m train.heldout", description="(re)write the index files "
                                     "of the held-out and the seen scenes under train/heldout_index/")
    parser.add_argument("data", type=pathlib.Path, help="folder of scene folders holding the held-out and the seen "
                        "scenes")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    write_indices(args.data)
    print("wrote " + ", ".join(str(p) for p in (*INDEX_FILES.values(), *SEEN_INDEX_FILES.values())))


if __name__ == "__main__":
    main()
