"""``codecsplat eval``: the paper's evaluation (Tables 1, 2 and 4) on scene folders or RE10K/ACID/DL3DV chunks.

For every scene sample (context views -> target views: from an evaluation index file with ``index``, which a
chunk folder needs, else picked by :func:`codecsplat_warp.data.split_context_targets` around evenly spread
anchors; see :mod:`codecsplat_warp.eval.protocols`):

* **CodecSplat** at each lambda: ``model.encode_scene`` -> bitstream -> ``model.decode_scene`` -> render the
  targets. Bytes are the whole bitstream (header, cameras, feature streams).
* **CodecSplat RDO** (``rdo_presets``, ``rdo_steps``): the same at each lambda with the encoder's rate-distortion
  optimisation (``model.encode_scene(..., preset=, steps=, seed=)``, :mod:`codecsplat_warp.model.rdo`), one row
  set per setting, e.g. method ``CodecSplat RDO (slow)``; with ``rdo_perceptual``, every setting once more with an
  LPIPS-VGG term of that weight in the loss (``CodecSplat RDO (slow, LPIPS 0.02)``).
* **Codec-free reference and baselines**, all on the same model's codec-free output (``model(images,
  cameras)``: Gaussians, ``F_c``, ``D_enc``): the Gaussians as an uncompressed float32 3DGS PLY (the
  reconstruction upper bound), (a) PLY attributes quantised + Deflate, (b) gsplat-style PNG, (c) the
  feature ``F_c`` (and depth) in float16 + Deflate, each encoded, decoded and rendered.
* **Image codecs + codec-free** (``webp``, ``jpeg``, at each quality): each context photograph (uint8 at the
  protocol size) coded as a WebP or JPEG file (:mod:`codecsplat_warp.baselines.image_codec`), decoded, and the
  codec-free model run on the decoded photographs with the true cameras. Bytes are the image files plus the
  header and camera bytes of the sample's CodecSplat bitstream: the cameras both sides must send.
* **Copy the nearest context view**: the floor every table shows, at zero bytes: each target is predicted
  by the context image whose camera centre is nearest to the target's, unchanged.

Metrics on the targets: PSNR (prediction clipped to [0,1]), SSIM (11x11 Gaussian window), LPIPS-VGG and
LPIPS-Alex (when weights are found); see :mod:`codecsplat_warp.metrics.image`.

Geometry (Table 3): every method with Gaussians also renders them into the sample's own context views, scored
with the same metrics against the context images (*self-render*; pixel-aligned Gaussians should give back
their images). With ``mvs_depth`` (``--mvs-depth DIR``: ``DIR/<scene>/depth.json`` of ``codecsplat depth``),
the codec-free encoder depth ``D_enc`` and each lambda's decoder depth ``D_hat`` are scored against the
reference depth of the context views (AbsRel, delta<1.25; :mod:`codecsplat_warp.eval.geometry`); samples whose
scene or context views have no reference are left out of the depth means, and ``depth_reference`` counts them.

Timing (Table 2, seconds; CUDA work is synchronised before a clock is read): *GS generation* is the
network work before compression: for CodecSplat the encoder's backbone up to ``F_c`` (MVEnc, FeatHead,
R_pre), for the baselines the whole codec-free forward pass that produces their Gaussians (for the image
codecs it runs at the receiver, on the decoded photographs); *compress* is the rest of the encoder
(CodecSplat: latent analysis, the RDO steps if any, entropy coding, bitstream) or the baseline's encoder;
*decompress* is bytes -> Gaussians on the device (for the image codecs: bytes -> photographs). A warm-up pass
on the first sample (Warp kernel loading, allocator, and one RDO step when RDO rows are asked for) is not
timed.

Outputs (``--out``): ``results.json`` (every sample and the summary; a rerun resumes from it), ``tables.md`` (Tables 1 and 2 in
the paper's form, Table 3), ``rate_distortion.png`` (PSNR, SSIM, LPIPS-VGG and LPIPS-Alex against bytes) and
``distortion_vs_time.png``; with ``--renders``, one picture per sample
under ``renders/`` (its target views against the ground truth, by every method, titled with bytes and PSNR).
"""

from __future__ import annotations

import contextlib
import json
import pathlib
import statistics
import sys
import time
from dataclasses import MISSING, asdict, dataclass, fields, replace
from typing import Callable, Collection, Iterator, NamedTuple, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from ..baselines import FeatureDeflate, ImageCodec, PlyDeflate, PngCompression
from ..choices import (BASELINE_NAMES, IMAGE_CODEC_QUALITIES, OUTPUT_BASELINES, PAPER_LAMBDAS,
                       RDO_CROSS_VIEW_MAX_VIEWS, RDO_CROSS_VIEW_MIN_STEPS, RDO_MIN_PRESET_STEPS, RDO_PRESETS)
from ..codec import bytes_report, check_lambda
from ..errors import DataError, InputError, NoSamplesError
from ..export.files import write_json, write_text
from ..export.ply import decode_ply, encode_ply
from ..export.video import to_uint8_frames
from ..gaussians import Gaussians
from ..measure import machine_name, synchronize, timed
from ..metrics.image import ImageMetrics
from ..metrics.lpips import weights_file
from ..model.codecsplat import model_id
from ..model.rdo import preset_steps, rdo_config
from .geometry import ReferenceDepth, depth_errors
from .protocols import (PROTOCOLS, Protocol, Sample, SamplePlan, chunk_plan, eager_plan, find_scenes, folder_index_plan,
                        is_chunk_folder, nearest_context_images, scene_samples, select_scenes)
from .report import (BACKBONE, CODECSPLAT, COPY_NEAREST, Row, format_bytes, image_codec_method, markdown_report,
                     plot_comparison, plot_distortion_vs_time, plot_rate_distortion, rdo_method, steps_text,
                     summarize, table1, table2, table3, table4)

SIDE_PARTS = ("header", "cameras")
"""Parts of a CodecSplat bitstream that the image-codec rows count too: the cameras both sides must send."""
BASE_GROUP = "base"
"""The row group of a sample's every row but the RDO rows (see :func:`row_layout`)."""


# --------------------------------------------------------------------------------------------------
# Running the methods
@dataclass(frozen=True)
class RDOSetting:
    """One encoder rate-distortion optimisation that ``codecsplat eval`` runs at every lambda: a ``preset`` of
    :data:`codecsplat_warp.choices.RDO_PRESETS`, or ``steps`` (which override the preset's count), with the
    quantisation-noise ``seed`` and the weight ``perceptual`` of an LPIPS-VGG term in the loss (0: none;
    :attr:`~codecsplat_warp.model.rdo.RDOConfig.perceptual_weight`).

    Raises:
        InputError: an unknown preset, steps that are not an integer >= 0, a setting without any step (the
            amortised encoder, whose rows every evaluation has), or a perceptual weight < 0.
    """

    preset: str = "fast"
    steps: int | None = None
    seed: int = 0
    perceptual: float = 0.0

    def __post_init__(self) -> None:
        if not rdo_config(self.preset, self.steps, seed=self.seed, perceptual_weight=self.perceptual).optimises:
            raise InputError(f"RDO setting {self.name!r} takes no optimisation step: it is the amortised encoder, "
                             "whose CodecSplat rows every evaluation has")

    @property
    def name(self) -> str:
        """``slow`` for a preset, ``N steps`` for a step count; ``slow, LPIPS 0.02`` with a perceptual term."""
        name = self.preset if self.steps is None else steps_text(self.steps)
        return name if self.perceptual == 0 else f"{name}, LPIPS {self.perceptual:g}"

    @property
    def method(self) -> str:
        """The method of its rows (``CodecSplat RDO (slow)``)."""
        return rdo_method(self.name)

    @property
    def resolved_steps(self) -> int | str:
        """The optimisation steps it takes: a count, or a preset's rule as :mod:`codecsplat_warp.choices` sets it now
        (``5 x views^2, at least 5; at least 160 with the cross-view term of up to 2 views``;
        :func:`~codecsplat_warp.model.rdo.preset_steps`)."""
        if self.steps is not None:
            return self.steps
        return (f"{RDO_PRESETS[self.preset]:g} x views^2, at least {RDO_MIN_PRESET_STEPS}; at least "
                f"{RDO_CROSS_VIEW_MIN_STEPS[self.preset]} with the cross-view term of up to "
                f"{RDO_CROSS_VIEW_MAX_VIEWS} views")

    def step_count(self, views: int) -> int:
        """The optimisation steps it takes with ``views`` context views."""
        return self.steps if self.steps is not None else preset_steps(self.preset, views)

    def encode_options(self, perceptual: torch.nn.Module | None) -> dict:
        """Keyword arguments of :meth:`CodecSplat.encode_scene`, with the LPIPS-VGG network ``perceptual`` that a
        perceptual term needs (InputError when it has one and ``perceptual`` is None)."""
        options = {"preset": self.preset, "steps": self.steps, "seed": self.seed}
        if self.perceptual == 0:
            return options
        if perceptual is None:
            raise InputError(f"RDO setting {self.name!r} needs the LPIPS-VGG weights: pass lpips_weights "
                             "(--lpips-weights) or set CODECSPLAT_LPIPS_WEIGHTS")
        return {**options, "rdo_settings": {"perceptual_weight": self.perceptual}, "perceptual": perceptual}

    def group(self, lam: float) -> str:
        """The row group of its row at ``lam`` (``slow λ=64``, see :func:`row_layout`)."""
        return f"{self.name} λ={lam:g}"


def row_layout(lambdas: Sequence[float], baselines: Collection[str], image_codecs: Sequence[ImageCodec],
               rdo: Sequence[RDOSetting]) -> list[str]:
    """The row group of each row :meth:`Evaluator.run` returns for a sample, in its order: :data:`BASE_GROUP` for
    copy-nearest and CodecSplat at each of ``lambdas``, each RDO setting's :meth:`~RDOSetting.group` at each lambda,
    then :data:`BASE_GROUP` for the codec-free reference, each of :data:`OUTPUT_BASELINES` in ``baselines`` and each
    image codec. An evaluation may produce some groups only (:attr:`EvalConfig.units`): the RDO rows, one encode
    each, are most of its time."""
    tail = 1 + sum(name in baselines for name in OUTPUT_BASELINES) + len(image_codecs)
    return ([BASE_GROUP] * (1 + len(lambdas)) + [setting.group(lam) for setting in rdo for lam in lambdas]
            + [BASE_GROUP] * tail)


def layout_rows(layout: list[str], groups: Collection[str] | None) -> list[int]:
    """The positions in a sample's ``layout`` (:func:`row_layout`) of the rows :meth:`Evaluator.run` returns for
    ``groups`` (None: every row), in the order it returns them."""
    return [i for i, group in enumerate(layout) if groups is None or group in groups]


@contextlib.contextmanager
def backbone_clock(model: torch.nn.Module, device: torch.device) -> Iterator[dict]:
    """Record in the yielded dict, under ``"features_done"``, the clock time when the backbone's last
    module (``model.refine_pre``, which outputs F_c) finishes: splits encoder time into GS generation and
    compression."""
    marks: dict[str, float] = {}

    def hook(*_):
        synchronize(device)
        marks["features_done"] = time.perf_counter()

    handle = model.refine_pre.register_forward_hook(hook)
    try:
        yield marks
    finally:
        handle.remove()


class Evaluator:
    """Runs every method on samples and scores the renders.

    Args:
        model: a :class:`CodecSplat` with its codec, in eval mode, on ``device``.
        metrics: the image metrics.
        lambdas: CodecSplat operating points.
        baselines: the baselines on the codec-free output to run, a subset of :data:`OUTPUT_BASELINES`.
        png: the PNG baseline with its settings (K_SH and Lloyd steps).
        keep_renders: keep each method's target renders of the last sample in :attr:`renders`.
        reference: reference depth of the context views (None: no depth errors).
        image_codecs: the image-codec rows, one per codec (format and quality).
        rdo: the RDO settings, each run at every lambda beside the amortised CodecSplat rows.

    Attributes:
        renders: after :meth:`run` with ``keep_renders``, one [T,H,W,3] uint8 array per returned row, in order.
    """

    def __init__(self, model, metrics: ImageMetrics, lambdas, baselines, device: torch.device,
                 png: PngCompression = PngCompression(), keep_renders: bool = False,
                 reference: ReferenceDepth | None = None, image_codecs: Sequence[ImageCodec] = (),
                 rdo: Sequence[RDOSetting] = ()):
        self.model = model
        self.reference = reference
        self.keep_renders = keep_renders
        self.renders: list[np.ndarray] = []
        self.metrics = metrics
        self.lambdas = [float(lam) for lam in lambdas]
        self.baselines = list(baselines)
        self.device = device
        self.ply_deflate = PlyDeflate()
        self.png = png
        self.feature = FeatureDeflate()
        self.image_codecs = list(image_codecs)
        self.rdo = list(rdo)

    def warm_up(self, sample: Sample) -> None:
        """Run the network, codec and renderer once, untimed (loads Warp kernels, warms allocators)."""
        sample = sample.to(self.device)
        with torch.no_grad(), self._autocast():
            self.model(sample.context_images, sample.context_cameras)
        data = self.model.encode(sample.context_images, sample.context_cameras, self.lambdas[0])
        self.model.render(self.model.decode(data), sample.target_cameras)
        if self.rdo:  # the optimisation's backward pass
            self.model.encode(sample.context_images, sample.context_cameras, self.lambdas[0], steps=1)

    def run(self, sample: Sample, progress: tqdm | None = None, groups: Collection[str] | None = None) -> list[Row]:
        """Every method's :class:`Row` on one sample, in the order of :func:`row_layout`; with ``groups``, only the
        rows of those row groups (:func:`row_layout`), the others not run."""
        reference = self.reference.context_depth(sample) if self.reference is not None else None
        sample = sample.to(self.device)
        rows = []
        self.renders = []

        def step(row: Row) -> Row:
            rows.append(row)
            if progress is not None:
                progress.update(1)
            return row

        base = groups is None or BASE_GROUP in groups
        if base:
            step(self._copy_nearest(sample))
            coded = [step(self._codecsplat(sample, lam, reference)) for lam in self.lambdas]
        for setting in self.rdo:
            for lam in self.lambdas:
                if groups is None or setting.group(lam) in groups:
                    step(self._codecsplat(sample, lam, reference, setting))
        if base:
            for row in self._reference_rows(sample, reference, coded[0]):
                step(row)
        return rows

    def _reference_rows(self, sample: Sample, reference: torch.Tensor | None, coded: Row) -> Iterator[Row]:
        """The rows after the CodecSplat ones, each when done: the codec-free reference, the baselines on its output
        and the image codecs (which count the side parts of ``coded``, a CodecSplat row of the sample)."""
        with torch.no_grad(), self._autocast():
            out, gen_s = timed(lambda: self.model(sample.context_images, sample.context_cameras), self.device)
        gaussians = out["gaussians"].detach()
        codec_free = self._gaussian_codec(sample, BACKBONE + "→PLY", "float32", gaussians, gen_s, encode_ply,
                                          decode_ply)
        yield replace(codec_free, depth=self._depth_errors(out["D_enc"], reference))  # the encoder depth D_enc
        if "ply" in self.baselines:
            yield self._gaussian_codec(sample, BACKBONE + "→PLY+Deflate", self.ply_deflate.setting, gaussians, gen_s,
                                       self.ply_deflate.encode, self.ply_deflate.decode)
        if "png" in self.baselines:
            yield self._gaussian_codec(sample, BACKBONE + "→PNG", self.png.setting, gaussians, gen_s,
                                       self.png.encode, self.png.decode)
        if "feature" in self.baselines:
            yield self._feature_codec(sample, out, gen_s, reference)
        side = {part: coded.parts[part] for part in SIDE_PARTS}  # the same at every lambda
        for codec in self.image_codecs:
            yield self._image_codec(sample, codec, side, reference)

    def _autocast(self):
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.device.type == "cuda")

    def _score(self, gaussians: Gaussians, sample: Sample) -> dict[str, float]:
        """Mean of each metric over the target views rendered from ``gaussians``."""
        with torch.no_grad():
            rgb = self.model.render(gaussians, sample.target_cameras)["rgb"]
        return self._score_rgb(rgb, sample)

    def self_render(self, gaussians: Gaussians, sample: Sample) -> dict[str, float]:
        """Mean of each metric over the context views rendered from ``gaussians``, against the context images."""
        with torch.no_grad():
            rgb = self.model.render(gaussians, sample.context_cameras)["rgb"]
        return {name: statistics.fmean(v) for name, v in self.metrics(rgb, sample.context_images).items()}

    @staticmethod
    def _depth_errors(depth: torch.Tensor, reference: torch.Tensor | None) -> dict[str, float]:
        """Errors of a method's depth map [V,H,W] against the context views' reference depth (empty without one)."""
        return {} if reference is None else depth_errors(depth, reference)

    def _score_rgb(self, rgb: torch.Tensor, sample: Sample) -> dict[str, float]:
        """Mean of each metric over the target views ``rgb`` [T,3,H,W] (kept when ``keep_renders``)."""
        if self.keep_renders:
            self.renders.append(to_uint8_frames(rgb))
        values = self.metrics(rgb, sample.target_images)
        return {name: statistics.fmean(v) for name, v in values.items()}

    def _copy_nearest(self, sample: Sample) -> Row:
        rgb = nearest_context_images(sample.context_images, sample.context_cameras, sample.target_cameras)
        return Row(sample.scene, COPY_NEAREST, "no bitstream", 0, self._score_rgb(rgb, sample), 0.0, 0.0, 0.0)

    def _codecsplat(self, sample: Sample, lam: float, reference: torch.Tensor | None,
                    rdo: RDOSetting | None = None) -> Row:
        """CodecSplat at ``lam``, amortised or with the encoder optimisation ``rdo`` (its steps are compress time)."""
        options = {} if rdo is None else rdo.encode_options(self.metrics.lpips.get("vgg"))
        with backbone_clock(self.model, self.device) as marks:
            synchronize(self.device)
            start = time.perf_counter()
            encoded = self.model.encode_scene(sample.context_images, sample.context_cameras, lam, **options)
            synchronize(self.device)
            end = time.perf_counter()
        decoded, decompress_s = timed(lambda: self.model.decode_scene(encoded.data), self.device)
        return Row(sample.scene, CODECSPLAT if rdo is None else rdo.method, f"λ={lam:g}", len(encoded.data),
                   self._score(decoded.gaussians, sample), gen_s=marks["features_done"] - start,
                   compress_s=end - marks["features_done"], decompress_s=decompress_s, lam=lam,
                   parts=bytes_report(encoded.data), self_render=self.self_render(decoded.gaussians, sample),
                   depth=self._depth_errors(decoded.depth, reference),
                   rdo=None if encoded.rdo is None else encoded.rdo.to_dict())

    def _image_codec(self, sample: Sample, codec: ImageCodec, side: dict[str, int],
                     reference: torch.Tensor | None) -> Row:
        """The context photographs through ``codec``, then the codec-free model on the decoded ones; ``side``: the
        bytes per part of :data:`SIDE_PARTS` that the row counts besides the image files."""
        photographs = to_uint8_frames(sample.context_images)
        files, compress_s = timed(lambda: codec.encode(photographs), self.device)
        images, decompress_s = timed(lambda: codec.decode(files, self.device), self.device)
        with torch.no_grad(), self._autocast():
            out, gen_s = timed(lambda: self.model(images, sample.context_cameras), self.device)
        gaussians = out["gaussians"].detach()
        parts = {**side, **{f"view{v}": len(data) for v, data in enumerate(files)}}
        parts["total"] = sum(parts.values())
        return Row(sample.scene, image_codec_method(codec.label), codec.setting, parts["total"],
                   self._score(gaussians, sample), gen_s, compress_s, decompress_s, parts=parts,
                   self_render=self.self_render(gaussians, sample),
                   depth=self._depth_errors(out["D_enc"], reference), quality=codec.quality)

    def _gaussian_codec(self, sample: Sample, method: str, setting: str, gaussians: Gaussians, gen_s: float,
                        encode: Callable, decode: Callable) -> Row:
        data, compress_s = timed(lambda: encode(gaussians), self.device)
        decoded, decompress_s = timed(lambda: decode(data, self.device), self.device)
        return Row(sample.scene, method, setting, len(data), self._score(decoded, sample), gen_s, compress_s,
                   decompress_s, self_render=self.self_render(decoded, sample))

    def _feature_codec(self, sample: Sample, out: dict, gen_s: float, reference: torch.Tensor | None) -> Row:
        data, compress_s = timed(lambda: self.feature.encode(out["F_c"], out["D_enc"], sample.context_cameras),
                                 self.device)

        def decode() -> tuple[Gaussians, torch.Tensor]:
            scene = self.feature.decode(data, self.device)
            with torch.no_grad(), self._autocast():
                return self.model.decode_gaussians(scene.feature, scene.depth, scene.cameras), scene.depth

        (decoded, depth), decompress_s = timed(decode, self.device)
        return Row(sample.scene, "CodecSplat w/ Deflate", self.feature.setting, len(data), self._score(decoded, sample),
                   gen_s, compress_s, decompress_s, self_render=self.self_render(decoded, sample),
                   depth=self._depth_errors(depth, reference))


# --------------------------------------------------------------------------------------------------
# Entry point
@dataclass
class EvalConfig:
    """Options of ``codecsplat eval`` (see :func:`evaluate`)."""

    data: str
    """A scene folder, a folder of scene folders, or a chunk folder (``index.json`` + ``*.torch``, needs ``index``)."""
    out: str = "codecsplat-eval"
    protocol: str = "re10k"
    lambdas: tuple[float, ...] = PAPER_LAMBDAS
    baselines: tuple[str, ...] = BASELINE_NAMES
    samples_per_scene: int = 1
    target_views: int | None = None
    lpips_weights: str | None = None
    png_sh_clusters: int = 8192
    kmeans_iterations: int = 10
    progress: bool = True
    scenes: tuple[str, ...] = ()
    """Scene folder names (or chunk scene keys) to keep; empty keeps every scene under ``data``."""
    index: str | None = None
    """Evaluation index file: the scenes and their context/target frames (``samples_per_scene`` unused)."""
    size: tuple[int, int] | None = None
    """(width, height) in pixels, each a multiple of 4, instead of the protocol's (its depth range and views stay)."""
    resume: bool = True
    """Keep the samples an earlier run of the same evaluation finished in ``out/results.json`` (False: start over)."""
    renders: bool = False
    """Also write ``renders/<scene>-<sample>.png`` per sample: targets x (ground truth, every method)."""
    mvs_depth: str | None = None
    """Folder of reference depth, ``<scene folder name>/depth.json`` per scene (``codecsplat depth``): scores the
    context views' depth maps (None: no depth errors)."""
    webp_qualities: tuple[int, ...] = IMAGE_CODEC_QUALITIES["webp"]
    """Qualities (0-100) of the WebP + codec-free rows, with ``webp`` in ``baselines``."""
    jpeg_qualities: tuple[int, ...] = IMAGE_CODEC_QUALITIES["jpeg"]
    """Qualities (1-100) of the JPEG + codec-free rows, with ``jpeg`` in ``baselines``."""
    rdo_presets: tuple[str, ...] = ()
    """Encoder RDO presets (:data:`codecsplat_warp.choices.RDO_PRESETS`, those with steps): each adds CodecSplat
    rows at every lambda, encoded with that optimisation."""
    rdo_steps: tuple[int, ...] = ()
    """RDO step counts (>= 1): each adds CodecSplat rows at every lambda, optimised for that many steps."""
    rdo_seed: int = 0
    """Seed of the RDO rows' quantisation noise."""
    rdo_perceptual: tuple[float, ...] = ()
    """Weights (> 0) of an LPIPS-VGG term in the RDO loss: each adds the rows of every RDO preset and step count
    once more, optimised with that term (needs the LPIPS weights, ``lpips_weights``)."""
    units: tuple[tuple[str, str], ...] = ()
    """(scene, row group) pairs (:func:`row_layout`: ``base`` or an RDO setting at a lambda, ``slow λ=64``): only
    the rows of those groups of each scene's samples, a worker's share of an evaluation dealt over processes
    (:func:`~codecsplat_warp.eval.shards.evaluate_sharded`); empty: every row."""
    plots: bool = True
    """Draw the rate-distortion and distortion-vs-time plots (a worker's share of an evaluation dealt over
    processes draws none, about 2.6 s each on a GPU host: the merge draws them)."""

    @property
    def image_qualities(self) -> dict[str, tuple[int, ...]]:
        """The qualities of each image-codec baseline, by its name in ``baselines``."""
        return {"webp": self.webp_qualities, "jpeg": self.jpeg_qualities}


RUN_SETTINGS = ("out", "progress", "resume", "renders", "plots")
"""EvalConfig fields that do not change the results: a run may resume another that differs only in these."""

CONFIG_DEFAULTS = {f.name: f.default for f in fields(EvalConfig) if f.default is not MISSING}
GEOMETRY_KEYS = {"self_render", "depth"}
"""Row keys of the self-render and depth measures, which results.json files written before them lack."""


def evaluate(model, config: EvalConfig, device: torch.device,
             on_sample: Callable[[int, int], None] | None = None) -> dict:
    """Evaluate ``model`` on every sample of ``config.data``; write results.json, tables.md and the plots.

    Scenes with too few views for the protocol are skipped and listed under ``skipped``. results.json is
    rewritten after every sample (``samples_done`` of ``samples_total``, and the ``plan``: every sample's scene,
    context and target frames), so an interrupted run keeps its rows; run again with the same options it
    resumes after the last finished sample (its rows, timings included, are kept as measured then). A chunk
    folder is streamed one chunk at a time (:func:`~codecsplat_warp.eval.protocols.chunk_plan`).

    A results.json of an earlier version, whose rows lack the self-render and depth measures, is not resumed:
    its samples are measured again, and ``notes`` says so.

    ``on_sample(done, total)``, when given, is called with the counts of finished and of all samples once the samples
    of an earlier run are known, and after every sample (e.g. to report progress to another process).

    With ``config.units``, each sample gives only the rows of the row groups its scene's units name (a worker's
    share, :func:`~codecsplat_warp.eval.shards.evaluate_sharded`), in their order of a full run.

    Returns:
        {"config", "device", "machine", "model_id", "scenes", "skipped", "lpips", "files", "plan", "rdo" (each RDO
        setting's method, preset, steps and seed), "samples_done", "samples_total", "summary", "rows",
        "depth_reference" (folder, samples and context views scored, and a sentence saying so), "notes", "tables"
        (table1, table2, table3, table4: the curves at equal bytes)}.
    Raises:
        InputError: unknown protocol or baseline, empty lambda list, bad size, a chunk folder without an index
            or with the ``scene`` protocol; an image baseline without qualities, a bad or repeated quality; an
            unknown, repeated or step-less RDO preset or step count; a unit of a row group the evaluation lacks.
        DataError: no usable scene (:class:`~codecsplat_warp.errors.NoSamplesError`); an index naming scenes or
            frames the data does not have; results.json of another evaluation in ``out`` (with ``resume``); a
            ``mvs_depth`` that is not a folder, or a corrupt ``depth.json`` or depth PNG in it.
    """
    protocol, png, image_codecs, rdo, layout = check_config(config)
    reference = ReferenceDepth(config.mvs_depth) if config.mvs_depth else None
    metrics = ImageMetrics(config.lpips_weights, device)
    plan = _plan(config, protocol, model)
    if not plan.keys:
        raise no_samples_error(config, protocol, plan.skipped)
    evaluator = Evaluator(model, metrics, config.lambdas, [b for b in config.baselines if b in OUTPUT_BASELINES],
                          device, png, keep_renders=config.renders, reference=reference, image_codecs=image_codecs,
                          rdo=rdo)
    out = pathlib.Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    files = result_files(out, config.plots)
    header = results_header(
        config, protocol, device, machine=machine_name(device), model=model_id(model), scenes=[k[0] for k in plan.keys],
        skipped=plan.skipped, lpips=metrics.lpips_missing or "LPIPS-VGG and LPIPS-Alex v0.1",
        plan=[[s, list(c), list(t)] for s, c, t in plan.keys],
        rdo=[{"method": s.method, "preset": s.preset, "steps": s.resolved_steps, "seed": s.seed,
              "perceptual": s.perceptual} for s in rdo])
    rows, start, notes = _finished(files["json"], header) if config.resume else ([], 0, [])
    for note in notes:
        tqdm.write(note, file=sys.stderr)
    total = len(plan.keys)
    if on_sample is not None:
        on_sample(start, total)
    methods = sum(len(layout_rows(layout, scene_groups(config, key[0]))) for key in plan.keys[start:])
    with tqdm(total=methods, desc="eval", unit="method",
              disable=None if config.progress else True) as progress:  # None: only on a terminal
        for done, sample in enumerate(plan.load(start), start + 1):
            if done == start + 1:
                evaluator.warm_up(sample)
            progress.set_postfix_str(sample.scene)
            sample_rows = evaluator.run(sample, progress, scene_groups(config, sample.scene))
            rows += sample_rows
            if config.renders:
                _write_renders(out / "renders" / f"{sample.scene}-{done}.png", sample, sample_rows, evaluator.renders)
            # after every sample, so an interrupted run keeps what it measured
            write_json(files["json"], {**header, "samples_done": done, "samples_total": total,
                                       "summary": summarize(rows), "rows": [asdict(r) for r in rows]})
            if on_sample is not None:
                on_sample(done, total)
    return write_results(header, rows, config.mvs_depth, notes)


class CheckedConfig(NamedTuple):
    """What :func:`check_config` makes of an :class:`EvalConfig`: the ``protocol`` (its target-view count and size
    applied), the ``png`` baseline, the ``image_codecs`` rows, the ``rdo`` settings and the ``layout`` of a
    sample's rows (:func:`row_layout`)."""

    protocol: Protocol
    png: PngCompression
    image_codecs: list[ImageCodec]
    rdo: list[RDOSetting]
    layout: list[str]


def check_config(config: EvalConfig) -> CheckedConfig:
    """Every option of ``config`` that needs no data, checked, and what the evaluation builds from them.

    Raises:
        InputError: unknown protocol or baseline, empty lambda list, a lambda outside [16, 1024], bad size,
            target-view or sample count, bad PNG baseline settings, bad image-codec qualities or RDO settings, RDO
            perceptual weights without the LPIPS-VGG weights file, a unit of a row group the evaluation does not
            have.
    """
    protocol = _protocol(config)
    unknown = sorted(set(config.baselines) - set(BASELINE_NAMES))
    if unknown:
        raise InputError(f"unknown baseline(s) {', '.join(unknown)}; choose from {', '.join(BASELINE_NAMES)}")
    if not config.lambdas:
        raise InputError("give at least one lambda")
    for lam in config.lambdas:
        check_lambda(lam)
    png = PngCompression(sh_clusters=config.png_sh_clusters, kmeans_iterations=config.kmeans_iterations)
    image_codecs, rdo = _image_codecs(config), _rdo_settings(config)
    if any(setting.perceptual > 0 for setting in rdo):
        weights_file("vgg", config.lpips_weights)  # the perceptual term's network, before hours of other rows
    layout = row_layout(config.lambdas, config.baselines, image_codecs, rdo)
    unknown = sorted({group for _, group in config.units} - set(layout))
    if unknown:
        raise InputError(f"units of unknown row groups {', '.join(unknown)}; this evaluation's are "
                         f"{', '.join(dict.fromkeys(layout))}")
    return CheckedConfig(protocol, png, image_codecs, rdo, layout)


def scene_groups(config: EvalConfig, scene: str) -> set[str] | None:
    """The row groups that ``config.units`` asks of the samples of ``scene`` (None: every row, without units)."""
    return {group for name, group in config.units if name == scene} if config.units else None


def no_samples_error(config: EvalConfig, protocol: Protocol, skipped: list[dict]) -> NoSamplesError:
    """The error of an evaluation without a sample: every scene ``skipped`` (``{"scene", "reason"}``), or none
    selected by the index."""
    reasons = "; ".join(f"{s['scene']}: {s['reason']}" for s in skipped) or "the index selects none"
    return NoSamplesError(f"no scene under {config.data} is usable with the {protocol.name} protocol: {reasons}",
                          skipped)


def result_files(out: pathlib.Path, plots: bool = True) -> dict[str, pathlib.Path]:
    """The files an evaluation writes in its output folder ``out``, by role (json, markdown, and with ``plots``
    rate_distortion, distortion_vs_time)."""
    files = {"json": out / "results.json", "markdown": out / "tables.md"}
    if plots:
        files.update(rate_distortion=out / "rate_distortion.png", distortion_vs_time=out / "distortion_vs_time.png")
    return files


def results_header(config: EvalConfig, protocol: Protocol, device: torch.device, *, machine: str, model: str,
                   scenes: list[str], skipped: list[dict], lpips: str, plan: list, rdo: list[dict]) -> dict:
    """The header of an evaluation's results, which :func:`write_results` completes: the config with its checked
    ``protocol`` (:func:`check_config`), the device and ``machine`` it ran on, the ``model`` id, the ``scenes``
    evaluated (sorted, once each) and those ``skipped``, the ``lpips`` note, the files it writes in ``config.out``,
    the ``plan`` (scene, context and target views of every sample, in order) and the ``rdo`` settings."""
    return {"config": {**asdict(config), "protocol": asdict(protocol)}, "device": str(device), "machine": machine,
            "model_id": model, "scenes": sorted(set(scenes)), "skipped": skipped, "lpips": lpips,
            "files": {role: str(path) for role, path in result_files(pathlib.Path(config.out), config.plots).items()},
            "plan": plan, "rdo": rdo}


def write_results(header: dict, rows: list[Row], mvs_depth: str | None, notes: list[str]) -> dict:
    """Finish an evaluation: ``header`` (config, device, machine, model_id, scenes, skipped, lpips, files and plan,
    as :func:`evaluate` writes them) with every sample's ``rows`` in the plan's order, their summary, the reference
    depth they cover (``mvs_depth``: the ``--mvs-depth`` folder or None), ``notes`` and the tables, written to the
    files ``header["files"]`` names (results.json, tables.md and, where it names them, the rate-distortion and
    distortion-vs-time plots).

    Returns:
        the result dict :func:`evaluate` returns.
    """
    summary = summarize(rows)
    total = len(header["plan"])
    result = {**header, "samples_done": total, "samples_total": total, "summary": summary,
              "rows": [asdict(r) for r in rows], "depth_reference": _depth_reference(mvs_depth, rows, header["plan"]),
              "notes": notes,
              "tables": {"table1": table1(summary), "table2": table2(summary), "table3": table3(summary),
                         "table4": table4(summary)}}
    files = {role: pathlib.Path(path) for role, path in header["files"].items()}
    write_json(files["json"], result)
    write_text(files["markdown"], markdown_report(result))
    if "rate_distortion" in files:
        plot_rate_distortion(summary, files["rate_distortion"])
        plot_distortion_vs_time(summary, files["distortion_vs_time"])
    return result


def _image_codecs(config: EvalConfig) -> list[ImageCodec]:
    """The image-codec rows of ``config``: each image baseline it names at each of its qualities.

    Raises:
        InputError: an image baseline without qualities, or with a repeated or bad one.
    """
    codecs = []
    for name in config.baselines:
        if name in IMAGE_CODEC_QUALITIES:
            qualities = config.image_qualities[name]
            if not qualities:
                raise InputError(f"give at least one {name} quality, or leave {name} out of the baselines")
            _once(qualities, f"{name} qualities")
            codecs += [ImageCodec(name, quality) for quality in qualities]
    return codecs


def _rdo_settings(config: EvalConfig) -> list[RDOSetting]:
    """The RDO settings of ``config``: its presets, then its step counts, then each of those again with each
    perceptual weight (InputError when one is bad or repeated, or perceptual weights come without a preset or a
    step count)."""
    _once(config.rdo_presets, "RDO presets")
    _once(config.rdo_steps, "RDO step counts")
    _once(config.rdo_perceptual, "RDO perceptual weights")
    plain = ([RDOSetting(preset=preset, seed=config.rdo_seed) for preset in config.rdo_presets]
             + [RDOSetting(steps=steps, seed=config.rdo_seed) for steps in config.rdo_steps])
    if config.rdo_perceptual and not plain:
        raise InputError("RDO perceptual weights need an RDO preset or step count to apply to (rdo_presets / "
                         "rdo_steps)")
    for weight in config.rdo_perceptual:
        if not weight > 0:
            raise InputError(f"RDO perceptual weights must be > 0 (the rows without the term are there anyway), "
                             f"got {weight:g}")
    return plain + [replace(setting, perceptual=float(weight)) for weight in config.rdo_perceptual
                    for setting in plain]


def _once(values: Sequence, what: str) -> None:
    """InputError naming the values that ``values`` repeats."""
    repeated = sorted({str(v) for v in values if list(values).count(v) > 1})
    if repeated:
        raise InputError(f"{what} must each be given once, got {', '.join(repeated)} more than once")


def _write_renders(path: pathlib.Path, sample: Sample, rows: list[Row], renders: list[np.ndarray]) -> None:
    """One sample's picture: its target views (rows) as the ground truth and each method's render (columns),
    titled with the method, bytes and PSNR."""
    titles = ["ground truth"] + [f"{row.method} {row.setting}\n{format_bytes(row.bytes)}, {row.metrics['psnr']:.2f} dB"
                                 for row in rows]
    plot_comparison([to_uint8_frames(sample.target_images)] + renders, titles, path)


def _plan(config: EvalConfig, protocol: Protocol, model) -> SamplePlan:
    """The samples of ``config.data``: an index's entries (chunks streamed, scene folders loaded when due), or
    ``samples_per_scene`` nearest-view splits of every scene folder (loaded at once, unusable ones skipped)."""
    if is_chunk_folder(config.data):
        if not config.index:
            raise InputError(f"{config.data} is a chunk folder: give the evaluation index of its scenes with --index "
                             "(e.g. DepthSplat's assets/evaluation_index_re10k.json)")
        return chunk_plan(config.data, config.index, protocol, config.scenes)
    if config.index:  # --scenes picks entries of the index
        return folder_index_plan(find_scenes(config.data), config.index, protocol, config.scenes)
    paths = select_scenes(find_scenes(config.data), tuple(sorted(config.scenes)))
    samples, skipped = [], []
    for path in paths:
        try:
            samples += scene_samples(path, protocol, protocol.context_views or model.config.num_views,
                                     config.samples_per_scene)
        except DataError as exc:
            skipped.append({"scene": path.name, "reason": str(exc)})
    return eager_plan(samples, skipped)


def plan_scenes(config: EvalConfig) -> list[str]:
    """The scenes of ``config.data`` that an evaluation visits, in its order, without decoding an image: the scene
    keys an index selects (a chunk folder, or ``index``), else the scene folders (those of ``scenes`` when given),
    those the protocol cannot use included (the evaluation skips them).

    Raises:
        InputError, DataError: as :func:`evaluate`, for bad options or data.
    """
    protocol = check_config(config).protocol
    if is_chunk_folder(config.data) or config.index:
        return list(dict.fromkeys(key[0] for key in _plan(config, protocol, None).keys))
    paths = select_scenes(find_scenes(config.data), tuple(sorted(config.scenes)))
    return list(dict.fromkeys(path.name for path in paths))


def _depth_reference(folder: str | None, rows: list[Row], keys: list) -> dict:
    """How many samples and context views the depth errors cover (read off the codec-free rows, one per
    sample), with a sentence that says so."""
    views = sum(len(context) for _, context, _ in keys)
    scored = [r.depth for r in rows if r.method == BACKBONE + "→PLY" and r.depth]
    counts = {"folder": folder, "samples": len(keys), "samples_scored": len(scored), "views": views,
              "views_scored": sum(d["views"] for d in scored)}
    text = ("No reference depth (no --mvs-depth)." if folder is None else
            f"Reference depth from {folder}: {len(scored)} of {len(keys)} sample(s) scored, "
            f"{counts['views_scored']} of {views} context views with reference depth; samples without any are left "
            "out of the depth means.")
    return {**counts, "text": text}


def _finished(file: pathlib.Path, header: dict) -> tuple[list[Row], int, list[str]]:
    """The rows and the count of the samples an earlier run of the same evaluation finished (none without a file),
    and notes: a file of an earlier version (rows without the self-render and depth measures) keeps none.

    Raises:
        DataError: ``file`` is not results JSON, or holds another evaluation (other options, model, device,
            LPIPS or samples), naming what differs.
    """
    if not file.exists():
        return [], 0, []
    try:
        saved = json.loads(file.read_text())
        rows, done = [Row(**r) for r in saved["rows"]], int(saved["samples_done"])
        measured = all(GEOMETRY_KEYS <= set(r) for r in saved["rows"])
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{file} is not the results of a codecsplat eval ({type(exc).__name__}: {exc}): "
                        "use another --out, or --restart to overwrite it") from None
    differs = [name for name, value in _identity(header).items() if _identity(saved).get(name) != value]
    if differs:
        raise DataError(f"{file} holds another evaluation ({', '.join(differs)} differ): use another --out, or "
                        "--restart to overwrite it")
    if not measured:
        return [], 0, [f"{file} predates the self-render and depth measures: its {done} finished sample(s) are "
                       "measured again"]
    return rows, done, []


def _identity(header: dict) -> dict:
    """What must match for a run to resume another: the options that change results, model, device, LPIPS, plan,
    and the steps each RDO setting takes (a preset's count may change between versions)."""
    config = header.get("config")
    if isinstance(config, dict):  # options added since a file was written read as their defaults
        config = {**CONFIG_DEFAULTS, **config}
        config = {k: v for k, v in config.items() if k not in RUN_SETTINGS}
        for key in ("data", "index", "mvs_depth"):
            if config.get(key):
                config[key] = str(pathlib.Path(config[key]).resolve())
        config = json.loads(json.dumps(config))  # tuples as lists, as read back from the file
    return {"options": config, "model": header.get("model_id"), "device": header.get("device"),
            "LPIPS": header.get("lpips"), "samples": header.get("plan"),
            "RDO steps": [s.get("steps") for s in header.get("rdo", [])]}


def _protocol(config: EvalConfig) -> Protocol:
    """The protocol of ``config`` with its target-view count and size options applied (InputError when bad)."""
    if config.protocol not in PROTOCOLS:
        raise InputError(f"unknown protocol {config.protocol!r}; choose one of {', '.join(PROTOCOLS)}")
    protocol = PROTOCOLS[config.protocol]
    if config.target_views is not None:
        if config.target_views < 1:
            raise InputError(f"target views must be >= 1, got {config.target_views}")
        protocol = replace(protocol, target_views=config.target_views)
    if config.size is not None:
        width, height = config.size
        if width < 4 or height < 4 or width % 4 or height % 4:
            raise InputError(f"size sides must be positive multiples of 4, got {width}x{height}")
        protocol = replace(protocol, width=width, height=height)
    if config.samples_per_scene < 1:
        raise InputError(f"samples per scene must be >= 1, got {config.samples_per_scene}")
    return protocol
