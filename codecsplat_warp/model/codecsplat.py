"""CodecSplat network (paper §3.2-3.5): the codec-free path of stage 1 and the codec path of stage 2.

Codec-free (``forward(images, cameras)``, stage 1)::

    images, cameras --MVEnc--> F_mv, P_depth, D_enc --FeatHead--> F_g --R_pre--> F_c
    (F_c, D_enc) --GSHead--> per-pixel Gaussians --Map 2D->3D--> world Gaussians --rasterize--> images

With the codec (``CodecSplat(config, codec=True)``; ``forward(images, cameras, lam)`` in stage 2,
:meth:`CodecSplat.encode` / :meth:`CodecSplat.decode` for bitstreams)::

    F_c --LatentCodec(lambda)--> latents (entropy coded, one stream per view) --> F^_c
    F^_c --DepthHead--> S, D^ ; F^_c + R_post(F^_c, A(F^_c, D^), S) --GSHead(., D^)--> Map 2D->3D --> Gaussians

The decoder side uses only the bitstream: its cameras, lambda and latents; never images or D_enc.

The *model identifier* (:func:`model_id`, 16 hex digits) names the decoder a bitstream needs: a hash of the
config, the float32 weights and the entropy coder's probability tables. Every bitstream carries it in its
header, and decoding with another model raises BitstreamError naming both and where to get the one it needs
(:func:`~codecsplat_warp.model.releases.where_to_get`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
from typing import Iterator

import numpy as np
import torch
from torch import nn
from torch.profiler import record_function

from ..cameras import Cameras
from ..checks import check_finite, check_tensor, common_device
from ..codec.bitstream import pack_bitstream, parse_bitstream
from ..codec.entropy import entropy_model_digest
from ..codec.latent import LatentCodec, check_lambda
from ..codec.scene import DecodedScene, EncodedScene
from ..device import resolve_device
from ..errors import BitstreamError, DeviceMismatchError, InputError
from ..gaussians import Gaussians
from ..measure import Timer, no_timer
from ..nn.config import FEATURE_STRIDE, MODEL_STRIDE, ModelConfig
from ..nn.mono import build_mono_backbone
from ..ops.raster import rasterize
from .feathead import FeatHead
from .heads import DepthHead, GaussianHead, map_to_world
from .culling import render_depth_range
from .mvenc import MonoBackbone, MVEnc, context_neighbours
from .rdo import optimise_latents, rdo_config
from .refine import Refiner
from .releases import where_to_get

DECODE_PRECISIONS = ("float32", "bfloat16")
"""Precisions :meth:`CodecSplat.decode_scene` runs its network part in; float32 is the default."""


class CodecSplat(nn.Module):
    """Feed-forward Gaussian generator and scene codec.

    Args:
        config: sizes (see :mod:`codecsplat_warp.nn.config` presets).
        mono_backbone: optional pretrained monocular feature extractor (see :class:`.mvenc.MonoBackbone`);
            default: the one ``config.mono`` names (random weights until a state dict or
            ``load_imagenet`` fills them), or none.
        codec: add the stage-2 modules (latent codec and post-codec refiner); a stage-1 model has none, so
            that each of its parameters takes part in the codec-free loss.

    The decoder's depth head exists in both: stage 1 trains it as an auxiliary on the detached F_c
    (towards the detached S_enc, ``S_aux`` of :meth:`forward` in training mode), so that stage 2 starts
    from a depth head that already reads depth from the feature it will decode.
    """

    def __init__(self, config: ModelConfig, mono_backbone: MonoBackbone | None = None, codec: bool = False):
        super().__init__()
        self.config = config
        self.mvenc = MVEnc(config, mono_backbone if mono_backbone is not None else build_mono_backbone(config.mono))
        self.feat_head = FeatHead(config)
        self.refine_pre = Refiner(config)
        self.gs_head = GaussianHead(config)
        self.depth_head = DepthHead(config)
        self.codec = LatentCodec(config) if codec else None
        self.refine_post = Refiner(config) if codec else None

    @property
    def has_codec(self) -> bool:
        """Whether the stage-2 modules exist (see ``codec`` of the constructor)."""
        return self.codec is not None

    CODEC_MODULE_NAMES = ("codec", "depth_head", "refine_post")
    """Attribute names of the stage-2 modules (:meth:`codec_modules`)."""

    def codec_modules(self) -> list[nn.Module]:
        """The stage-2 modules (trained in stage 2, the rest frozen): codec, depth head, post-codec refiner."""
        self._require_codec()
        return [getattr(self, name) for name in self.CODEC_MODULE_NAMES]

    def forward(self, images: torch.Tensor, cameras: Cameras, lam: float | None = None, scenes: int = 1) -> dict:
        """Run the codec-free path, or with ``lam`` the codec path (stage 2, differentiable).

        Args:
            images: [V,3,H,W] float in [0,1], V >= 2, H and W multiples of 4 equal to the cameras' size.
            cameras: the V context cameras, on the model's device.
            lam: None for the codec-free path; a rate-distortion lambda in [16, 1024] for the codec path
                (noisy quantisation in training mode, the coder's rounding in eval mode).
            scenes: the V views are this many scenes of V / scenes consecutive views each (a training batch):
                views attend to, match against and refine with views of their own scene only, and the
                Gaussians are view-major, so :meth:`Gaussians.split` gives each scene's.

        Returns:
            dict with ``F_mv`` [V,C,H/4,W/4], ``P_depth`` [V,D,H/4,W/4], ``F_g`` and ``F_c`` [V,C_F,H/2,W/2],
            ``D_enc`` [V,H,W] (metric, in [near, far]), ``S_enc`` [V,H,W] (Eq. 18, in [0,1]), ``neighbours``
            [V,M] and ``gaussians`` (:class:`Gaussians`, N = V*H*W, float32): codec-free from (F_c, D_enc),
            or with ``lam`` decoded from F^_c; with ``lam`` also ``F_hat`` [V,C_F,H/2,W/2] (F^_c), ``S`` and
            ``D_hat`` [V,H,W] (decoder depth, Eqs. 9-10), ``rate_bits`` (scalar, estimated bits of all views) and
            ``latents`` (per level, the posterior means on the gained grid that were quantised);
            codec-free in training mode also ``S_aux`` [V,H,W], the depth head's S on the detached F_c.

        Raises:
            InputError: bad shape, dtype, size or values, lambda out of range, ``lam`` without a codec;
            DeviceMismatchError: inputs not on the model's device.
        """
        images = self._check_inputs(images, cameras)
        neighbours = context_neighbours(cameras, self.config.neighbours, scenes)
        enc = self.mvenc(images, cameras, neighbours)
        f_g = self.feat_head(images, enc.features, enc.prob)
        f_c = self.refine_pre(f_g, enc.depth, cameras, enc.neighbours)
        out = {"F_mv": enc.features, "P_depth": enc.prob, "F_g": f_g, "F_c": f_c, "D_enc": enc.depth,
               "S_enc": enc.normalized_depth, "neighbours": enc.neighbours}
        if lam is None:
            out["gaussians"] = self.decode_gaussians(f_c, enc.depth, cameras)
            if self.training:
                out["S_aux"] = self.depth_head(f_c.detach(), cameras)[0]
            return out
        self._require_codec()
        coded = self.codec(f_c, lam)
        s, depth, gaussians = self.decode_feature(coded.feature, cameras, enc.neighbours)
        out.update(F_hat=coded.feature, S=s, D_hat=depth, rate_bits=coded.bits.sum(), gaussians=gaussians,
                   latents=coded.latents)
        return out

    def decode_feature(self, feature: torch.Tensor, cameras: Cameras,
                       neighbours: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, Gaussians]:
        """§3.5 from the reconstructed feature F^_c [V,C_F,H/2,W/2]: depth head (S, D^ [V,H,W]), post-codec
        refiner with A(F^_c, D^) (Eq. 5), GS head, Map 2D->3D. ``neighbours`` [V,M] default to the cameras'
        nearest views (as MVEnc picks them). Returns (S, D^, Gaussians)."""
        with record_function("depth_head"):
            s, depth = self.depth_head(feature, cameras)
        if neighbours is None:
            neighbours = context_neighbours(cameras, self.config.neighbours)
        with record_function("refine_post"):
            refined = self.refine_post(feature, depth, cameras, neighbours)
        return s, depth, self.decode_gaussians(refined, depth, cameras)

    def decode_gaussians(self, feature: torch.Tensor, depth: torch.Tensor, cameras: Cameras) -> Gaussians:
        """Eqs. 11-12: GSHead(feature [V,C_F,H/2,W/2], depth [V,H,W]) then Map 2D->3D -> world Gaussians."""
        with record_function("gs_head"):
            pixels = self.gs_head(feature, depth, cameras)
        with record_function("map_to_world"), torch.autocast(feature.device.type, enabled=False):
            return map_to_world(pixels, depth.float(), cameras)  # world positions and SH rotations in float32

    # ----------------------------------------------------------------------------------------------
    # Bitstreams
    @torch.no_grad()
    def encode_scene(self, images: torch.Tensor, cameras: Cameras, lam: float, timer: Timer = no_timer,
                     preset: str = "fast", steps: int | None = None, time_budget: float | None = None,
                     seed: int = 0, progress: bool = False, rdo_settings: dict | None = None,
                     perceptual: nn.Module | None = None, on_check=None, refiner: nn.Module | None = None
                     ) -> EncodedScene:  # fmt: skip
        """Encoder: context views -> scene bitstream (Eq. 8) and the coded symbols.

        MVEnc, FeatHead and R_pre give F_c (bf16 autocast on CUDA), the codec quantises and range codes its
        latents, and the bitstream packs them with the cameras (at the model's float precision) and lambda
        (as float32, the value the decoder will use). With a ``preset`` other than ``"fast"``, or ``steps`` > 0,
        or a ``time_budget``, the latents are then optimised for this scene through the fixed decoder
        (rate-distortion optimisation, :mod:`.rdo`): the bitstream format and the decoder stay the same. Ctrl-C
        during the optimisation ends it early with the best latents measured so far (``rdo.stopped`` says so).
        ``timer`` times the phases ``entropy``, ``rdo`` and ``bitstream`` (benchmarks; the rest is network time).

        Args:
            images: [V,3,H,W] in [0,1]; cameras: the V context cameras (both on the model's device).
            lam: rate-distortion trade-off in [16, 1024]; larger is more bytes and better quality.
            preset: ``"fast"`` (the amortised encoder alone), ``"medium"`` or ``"slow"``: optimisation steps that grow
                with the square of the view count (:func:`.rdo.preset_steps`; 25 and 160 steps for 2 views, whose
                loss has a cross-view term, 80 and 320 for 8).
            steps: optimisation steps, overriding the preset's (0: none).
            time_budget: wall seconds the optimisation may take at most (None: no limit).
            seed: seed of the optimisation's quantisation noise (the same seed repeats a run on the CPU).
            progress: show the optimisation's progress bar (on a terminal).
            rdo_settings: other fields of :class:`.rdo.RDOConfig` (learning rate, loss weights, precision, ...)
                for experiments; None keeps the tuned defaults.
            perceptual: the perceptual network (LPIPS) of a perceptual term (``perceptual_weight`` > 0).
            on_check: called with every real coding the optimisation measures (:func:`.rdo.optimise_latents`).
            refiner: a learned refiner of the latents trained for this model (:func:`.rdo.load_refiner`): each
                optimisation step is one of its iterations instead of an Adam step (``steps`` or the preset's
                count of them).
        Raises:
            InputError / DeviceMismatchError: as :meth:`forward`; InputError if the model has no codec, for an
                unknown preset, steps < 0 or a time budget <= 0.
        """
        self._require_codec()
        lam = float(np.float32(check_lambda(lam)))
        config = rdo_config(preset, steps, time_budget, seed, cameras.num_views, **(rdo_settings or {}))
        images = self._check_inputs(images, cameras)
        with torch.autocast(images.device.type, dtype=torch.bfloat16, enabled=images.device.type == "cuda"):
            enc = self.mvenc(images, cameras)
            f_g = self.feat_head(images, enc.features, enc.prob)
            f_c = self.refine_pre(f_g, enc.depth, cameras, enc.neighbours)
            compressed = self.codec.compress(f_c, lam, timer, reconstruct=config.optimises)
        result = None
        if config.optimises:
            with timer("rdo"), torch.enable_grad():
                result = optimise_latents(self, images.float(), cameras.to(dtype=torch.float32), lam, compressed,
                                          config, progress, perceptual, on_check, f_c.float(), refiner)
            compressed = result.compressed
        with timer("bitstream"):
            data = pack_bitstream(model_id(self), lam, cameras.to(dtype=self._dtype()), compressed.streams)
        return EncodedScene(data, [len(s) for s in compressed.streams], compressed.symbols, compressed.bits, result)

    def encode(self, images: torch.Tensor, cameras: Cameras, lam: float, preset: str = "fast",
               steps: int | None = None, time_budget: float | None = None, seed: int = 0,
               progress: bool = False, refiner: nn.Module | None = None) -> bytes:
        """The scene bitstream of :meth:`encode_scene` (self-contained: cameras and lambda inside)."""
        return self.encode_scene(images, cameras, lam, preset=preset, steps=steps, time_budget=time_budget,
                                 seed=seed, progress=progress, refiner=refiner).data

    @torch.no_grad()
    def decode_scene(self, data: bytes, device=None, timer: Timer = no_timer,
                     precision: str = "float32") -> DecodedScene:  # fmt: skip
        """Decoder (§3.5): bitstream -> latents -> F^_c -> depth head -> R_post -> GS head -> Gaussians.

        Uses only the bitstream (cameras, lambda, latents). Runs on the model's device, in the model's float dtype
        whatever autocast the caller runs under, so that every device decodes a bitstream to the same Gaussians
        up to float32 rounding (the latents are bit-exact on every device; the float64 prior path is fixed).
        ``timer`` times ``bitstream`` (parsing) and ``entropy``.

        Args:
            data: a bitstream written by :meth:`encode` with this model.
            device: where to decode; None for the model's device, otherwise it must be that device.
            precision: ``"float32"``, or ``"bfloat16"`` to run the network part under bf16 autocast (an opt-in
                for speed on a GPU: its Gaussians differ from the float32 decode's, means by up to ~0.3 world
                units on real scenes, so another device's decode no longer matches it).
        Raises:
            BitstreamError: truncated, corrupt, foreign (another model's: the message says where that model is), or
                newer-version input.
            DeviceMismatchError: ``device`` is not the model's device.
            InputError: an unknown ``precision``.
        """
        self._require_codec()
        if precision not in DECODE_PRECISIONS:
            raise InputError(f"precision must be one of {DECODE_PRECISIONS}, got {precision!r}")
        param = next(self.parameters())
        if device is not None and not _same_device(resolve_device(device), param.device):
            raise DeviceMismatchError(f"decode on {resolve_device(device)} needs the model there (it is on "
                                      f"{param.device}): move it with model.to(device)")
        with timer("bitstream"):
            parsed = parse_bitstream(data)
            expected = model_id(self)
            if parsed.header.model_id != expected:
                raise BitstreamError(f"the bitstream was written by model {parsed.header.model_id}, but this model is "
                                     f"{expected}; {where_to_get(parsed.header.model_id)}")
        cameras = parsed.cameras.to(param.device, param.dtype)
        grid_h, grid_w = cameras.height // FEATURE_STRIDE, cameras.width // FEATURE_STRIDE
        full_float32 = _without_tf32() if precision == "float32" else contextlib.nullcontext()
        with full_float32, torch.autocast(param.device.type, dtype=torch.bfloat16, enabled=precision == "bfloat16"):
            feature, latents = self.codec.decompress(parsed.feature_streams, grid_h, grid_w, parsed.header.lam, timer)
            _, depth, gaussians = self.decode_feature(feature, cameras)
        return DecodedScene(gaussians=gaussians, cameras=cameras, depth=depth, lam=parsed.header.lam,
                            header=parsed.header, latents=latents)

    def decode(self, data: bytes, device=None) -> Gaussians:
        """The Gaussians of :meth:`decode_scene`."""
        return self.decode_scene(data, device).gaussians

    def render(self, gaussians: Gaussians, cameras: Cameras, background: torch.Tensor | None = None,
               render_depth: bool = False, depth_range: tuple[float, float] | None = None,
               leave_out: torch.Tensor | None = None) -> dict:
        """Rasterize ``gaussians`` into B target ``cameras`` (float32, autocast off), culling outside
        ``depth_range`` (default :func:`render_depth_range` of the cameras, which reads their bounds on the host:
        loops that render into the same cameras pass it once). ``leave_out`` [B,2]: camera b renders without the
        Gaussians ``leave_out[b,0] <= n < leave_out[b,1]`` (:func:`~codecsplat_warp.ops.raster.rasterize`; e.g. a
        view predicted from the other views' Gaussians, :meth:`Gaussians.view_ranges`).

        Returns:
            dict with ``rgb`` [B,3,H,W], ``alpha`` [B,H,W], ``depth`` [B,H,W] (None unless ``render_depth``)
            and the rasterizer's ``meta``.
        """
        common_device(means=gaussians.means, K=cameras.K)
        cams = cameras.to(dtype=torch.float32)
        near, far = depth_range or render_depth_range(cams)
        with record_function("rasterize"), torch.autocast(gaussians.means.device.type, enabled=False):
            rgb, depth, alpha, meta = rasterize(
                gaussians.means.float(), gaussians.quats.float(), gaussians.scales.float(),
                gaussians.opacities.float(), gaussians.sh.float(), cams.w2c, cams.K, cams.width, cams.height,
                near=near, far=far, background=background, mode="classic", sh_degree=gaussians.sh_degree,
                render_depth=render_depth, leave_out=leave_out,
            )
        # views all three; squeeze's gradient is a view too, where indexing's would zero and copy a new tensor
        return {"rgb": rgb.permute(0, 3, 1, 2), "alpha": alpha.squeeze(-1),
                "depth": depth.squeeze(-1) if depth is not None else None, "meta": meta}

    def render_own_views(self, gaussians: Gaussians, cameras: Cameras) -> torch.Tensor:
        """[V,3,H,W]: each context view's own Gaussians rendered alone into its own camera (float32).

        ``gaussians`` are the pixel-aligned Gaussians of the V ``cameras``, view-major (V equal pieces, as
        :meth:`forward` makes them; a training batch's views of several scenes included). Raises InputError unless
        there are V*H*W of them.
        """
        expected = cameras.num_views * cameras.height * cameras.width
        if len(gaussians) != expected:
            raise InputError(f"render_own_views needs the pixel-aligned Gaussians of the {cameras.num_views} views, "
                             f"{expected} (V*H*W), got {len(gaussians)}")
        pieces = gaussians.split(cameras.num_views)
        return torch.cat([self.render(piece, cameras.select([v]))["rgb"] for v, piece in enumerate(pieces)])

    def _require_codec(self) -> None:
        if not self.has_codec:
            raise InputError("this CodecSplat has no codec (a stage-1 model, built with codec=False): build it with "
                             "codec=True and train stage 2, or use load_pretrained()")

    def _dtype(self) -> torch.dtype:
        return next(self.parameters()).dtype

    def _check_inputs(self, images: torch.Tensor, cameras: Cameras) -> torch.Tensor:
        if not isinstance(cameras, Cameras):
            raise InputError(f"cameras must be a codecsplat_warp.cameras.Cameras, got {type(cameras).__name__}")
        V = cameras.num_views
        images = check_tensor("images", images, (V, 3, cameras.height, cameras.width),
                              (torch.float32, torch.float64, torch.bfloat16, torch.float16))
        if V < 2:
            raise InputError(f"images must hold at least 2 context views (multi-view matching), got {V}")
        H, W = images.shape[-2:]
        if H % MODEL_STRIDE or W % MODEL_STRIDE:
            raise InputError(f"images height and width must be multiples of {MODEL_STRIDE}, got {H}x{W}")
        param = next(self.parameters())
        if images.device != param.device or cameras.device != param.device:
            raise DeviceMismatchError(f"images on {images.device} and cameras on {cameras.device} must be on the "
                                      f"model's device {param.device}")
        check_finite("images", images)
        if bool(images.min() < 0) or bool(images.max() > 1):
            raise InputError("images must hold values in [0, 1]")
        return images.to(param.dtype)


@contextlib.contextmanager
def _without_tf32() -> Iterator[None]:
    """Float32 convolutions and matmuls on CUDA in full float32 inside the block: cuDNN takes TF32 (10 mantissa
    bits) for float32 convolutions by default, which would move a CUDA decode away from the CPU's by ~1e-3."""
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def weights_digest(model: torch.nn.Module) -> str:
    """SHA-256 hex of a model's config and state dict (names, shapes, float32 little-endian values).

    Cached on the model until a tensor changes (new storage or an in-place update such as an optimizer step).
    """
    state = model.state_dict()
    key = tuple((name, t.data_ptr(), t._version, str(t.device), t.dtype) for name, t in state.items())
    cached = getattr(model, "_weights_digest_cache", None)
    if cached is not None and cached[0] == key:
        return cached[1]
    sha = hashlib.sha256(json.dumps(model.config.to_dict(), sort_keys=True).encode())
    for name in sorted(state):
        tensor = state[name].detach().to("cpu", torch.float32).contiguous()
        sha.update(f"{name}:{tuple(tensor.shape)}".encode())
        sha.update(tensor.numpy().astype("<f4").tobytes())
    digest = sha.hexdigest()
    model._weights_digest_cache = (key, digest)
    return digest


def model_id(model: torch.nn.Module) -> str:
    """16 hex digits naming the decoder: hash of :func:`weights_digest` and the entropy coder's tables."""
    return hashlib.sha256((weights_digest(model) + entropy_model_digest()).encode()).hexdigest()[:16]


def _same_device(a: torch.device, b: torch.device) -> bool:
    """Whether two torch devices are the same (``cuda`` without an index is the current CUDA device)."""
    index = lambda d: torch.cuda.current_device() if d.type == "cuda" and d.index is None else d.index  # noqa: E731
    return a.type == b.type and (a.type == "cpu" or index(a) == index(b))
