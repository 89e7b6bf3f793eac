"""The models this package has shipped, by model identifier, and where a user finds each one.

Every bitstream names the model that wrote it (:func:`~codecsplat_warp.model.codecsplat.model_id`, 16 hex digits)
and only that model decodes it. When the shipped default changes, bitstreams written with an earlier default stay
decodable with that model's file, and :func:`where_to_get` tells a user who holds one where that file is.
"""

from __future__ import annotations

DEFAULT_MODEL_ID = "554cc15fd43d1f3e"
"""The identifier of the model shipped with this package (the file :data:`DEFAULT_FILE`; a test checks that it
holds this model)."""

EARLIER_DEFAULTS: dict[str, str] = {}
"""Models that were the shipped default of an earlier release and are no longer: identifier -> the last
``codecsplat-warp`` version that shipped it (empty while the first default ships)."""

DEFAULT_FILE = "assets/codecsplat-default.safetensors"
"""Where a release keeps its default model, relative to the package folder ``codecsplat_warp/``
(:data:`~codecsplat_warp.model.pretrained.DEFAULT_CHECKPOINT` is this file)."""


def where_to_get(model_id: str) -> str:
    """One sentence saying how to decode with the model ``model_id`` (16 hex digits): the shipped default, an
    earlier release's default (its version, and the file inside it), or a model file of the user's own."""
    if model_id == DEFAULT_MODEL_ID:
        return (f"{model_id} is the model shipped with this package: decode without --checkpoint (Python: "
                "load_pretrained())")
    if model_id in EARLIER_DEFAULTS:
        version = EARLIER_DEFAULTS[model_id]
        return (f"{model_id} was the default model of codecsplat-warp {version}: decode with that release (pip "
                f"install codecsplat-warp=={version}), or pass its codecsplat_warp/{DEFAULT_FILE} as --checkpoint (Python: "
                "load_pretrained(path))")
    return (f"{model_id} is not a model this package shipped: decode with the model file that encoded it "
            "(--checkpoint FILE; Python: load_pretrained(FILE))")
