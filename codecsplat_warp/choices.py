"""Names and defaults that the command line offers and the library uses, in a module without imports.

``codecsplat --help`` builds its parser from these (and from :mod:`codecsplat_warp.bench.options`) without
importing torch or Warp, so that it, every subcommand's ``--help`` and a bad argument answer at once; the modules
that use them import them from here.
"""

from __future__ import annotations

DEMO_SCENE = "nerd_mary_rose"
"""The scene ``codecsplat demo`` runs on by default: photographs shipped with the package."""

PROCEDURAL = "procedural"
"""``--scene`` name of the procedural room."""

DEMO_SEED = 3
"""Seed of ``codecsplat demo``'s procedural scene."""

DEMO_LAMBDAS = (16.0, 128.0, 1024.0)
"""Rate trade-offs ``codecsplat demo`` encodes at."""

DEMO_TARGET_VIEWS = 2
"""Target views ``codecsplat demo`` renders and scores."""

DEMO_RDO_STEPS = 10
"""Encoder rate-distortion optimisation steps of the demo's extra bitstream at its largest lambda (about 30 s on a
2-core CPU for the shipped scene's two views; 0 leaves it out)."""

OUTPUT_BASELINES = ("ply", "png", "feature")
"""Baselines that compress the codec-free model's output: (a) PLY + Deflate, (b) PNG, (c) float16 feature + Deflate."""

IMAGE_CODEC_QUALITIES = {"webp": (0, 10, 35, 80), "jpeg": (1, 5, 20, 50)}
"""Baselines that code the context photographs as image files (then the codec-free model runs on the decoded ones),
with the qualities ``codecsplat eval`` runs by default (``--webp-qualities``, ``--jpeg-qualities``): on the ten
held-out scenes about 2-15 KiB per scene for 2 views at 256x256 and 12-104 KiB for 8 views at 256x448."""

BASELINE_NAMES = OUTPUT_BASELINES + tuple(IMAGE_CODEC_QUALITIES)
"""Baselines ``--baselines`` may name."""

PAPER_LAMBDAS = (16.0, 32.0, 64.0, 128.0, 256.0, 512.0, 1024.0)
"""The paper's rate trade-offs (``codecsplat eval``'s default)."""

PROTOCOL_NAMES = ("re10k", "dl3dv", "scene")
"""The evaluation protocols, the keys of :data:`codecsplat_warp.eval.protocols.PROTOCOLS`."""

FRAME_FORMATS = ("png", "gif", "mp4")
"""Output formats of rendered frames (:func:`codecsplat_warp.export.video.write_frames`)."""

RDO_PRESETS = {"fast": 0.0, "medium": 1.25, "slow": 5.0}
"""Encoder rate-distortion optimisation presets: optimisation steps per squared context view count (``fast``: none,
the amortised encoder alone; see :func:`codecsplat_warp.model.rdo.preset_steps`). On the held-out scenes the target
views' gain peaked after about 20 steps with 2 views (with the context views alone in the loss) and still rose after
300 with 8 (H100, docs/benchmarks.md): the useful step count grows with about the square of the view count. With the
cross-view term of 2-view scenes the least counts are :data:`RDO_CROSS_VIEW_MIN_STEPS`."""

RDO_MIN_PRESET_STEPS = 5
"""The fewest steps of a preset that optimises."""

RDO_CROSS_VIEW_MAX_VIEWS = 2
"""Scenes of at most this many context views get the cross-view term in the RDO loss (each view predicted by the
other views' Gaussians; :func:`codecsplat_warp.model.rdo.cross_view_error`). With 2 views it keeps the fit from
explaining each photograph with geometry the other view does not confirm, so the targets keep gaining with steps;
with 8 views, where every view's render already mixes all views' Gaussians, it gained nothing for 80 % more time a
step (docs/benchmarks.md)."""

RDO_CROSS_VIEW_WEIGHT = 0.5
"""The cross-view term's weight for the scenes of :data:`RDO_CROSS_VIEW_MAX_VIEWS` (0.5 beat 1 and 2 in PSNR and
bytes on the held-out scenes)."""

RDO_CROSS_VIEW_MIN_STEPS = {"medium": 25, "slow": 160}
"""The fewest steps of each optimising preset when the cross-view term is on: with it the 2-view targets still
gained at 160 steps, where without it they peaked near 20. ``medium`` takes less than a quarter of ``slow``'s steps
because a run's fixed cost (the decoder's capture, the real codings) made 40 steps 31 % of ``slow``'s time."""

RDO_PERCEPTUAL_WEIGHT = 0.02
"""The LPIPS-VGG weight of ``codecsplat encode --perceptual`` given without a value: on the held-out RE10K samples
(2 views, ``slow``) it took LPIPS-VGG below WebP's at every size for 19-29 % more bytes and at most 0.2 dB of PSNR;
0.05 gained little more LPIPS for more bytes (docs/evaluation.md)."""
