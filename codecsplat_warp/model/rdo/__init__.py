"""Encoder-side rate-distortion optimisation (RDO): the coded latents fitted per scene through the fixed decoder.

The amortised encoder (MVEnc, FeatHead, R_pre, the codec's analysis and posterior) predicts the latents in one pass.
The encoder also has the context photographs, and the decoder (the codec's top-down pass and synthesis, the depth
head, R_post with the Warp reprojection, the GS head, the Warp unprojection and rasterizer) is differentiable end
to end, so the latents can be optimised against what the decoder will make of them. Nothing in the model, the
decoder or the bitstream format changes: the optimised latents are coded by the same range coder, under the same
priors, and any decoder of the model decodes them.

What is optimised: the posterior means of every latent level on the gained grid (one quantisation step = 1), starting
from the amortised ones, with Adam; or (``RDOConfig.variable="feature"``) the encoder's F_c, which the codec's
analysis and posterior turn into the latents. Per step (:func:`rdo_loss`), with the codec's training quantiser (straight-through
rounding towards the decoder, noisy rate), the loss is

    (lambda / 1024) * [MSE(decoded Gaussians rendered into the context cameras, context images)
                       + perceptual_weight * LPIPS(the same renders, context images)
                       + cross_view_weight * (each context view predicted by the OTHER views' Gaussians alone:
                                              their colour over their alpha against the photograph, weighted by
                                              that alpha)
                       + depth_weight * |S - S_amortised|_1]
    + rate_weight * (estimated bits / context pixels) + anchor_weight * mean((z - z_amortised)^2)

The tuned settings (:func:`rdo_config`) use the first term, the rate and, for scenes of at most
:data:`~codecsplat_warp.choices.RDO_CROSS_VIEW_MAX_VIEWS` views, the cross-view term: without it the 2-view targets'
gain peaked after some 20 steps while the context views kept improving (the photographs got fitted with geometry
that no other view confirms); with it they still gain at 160 steps. With eight views the term gained nothing and the
targets still gain after 300 steps without it: the presets' step counts grow with the square of the view count
(:func:`preset_steps`). On the held-out scenes the depth term and the anchor lowered the targets' PSNR, and the
LPIPS term trades PSNR and bytes for LPIPS and needs the LPIPS weights (docs/benchmarks.md, "Encoder RDO"); they
stay for experiments (``codecsplat bench rdo --set``).

Every ``check_every`` steps and at the end, the current latents are coded for real (the coder's rounding, the
float64 prior path; :meth:`LatentCodec.compress_latents`) and scored by the same loss, with the discrete model's
bits: the encoder keeps the best latents it has measured (the amortised ones are step 0), not just the last. It
has no target views: this is the loss it can measure.

Robustness: gradients that are not finite are zeroed, latents are clamped to +-:data:`LATENT_LIMIT` (far inside the
coder's escape range), a check whose loss is not finite ends the run, and Ctrl-C (KeyboardInterrupt) during the
steps ends it too: in every case the best latents measured so far are returned (:attr:`RDOResult.stopped` says
why). With the same ``seed`` two runs on the CPU give the same latents.

One concept a module: :mod:`.presets` (the presets and :class:`RDOConfig`), :mod:`.loss` (the decoder from the
optimised tensors and :func:`rdo_loss`), :mod:`.graphs` (the CUDA graphs of a run), :mod:`.refiner` (a learned
refiner of the latents, :class:`LatentRefiner`, whose iterations can replace Adam's steps) and :mod:`.loop` (the run,
:func:`optimise_latents`, and its steps without checks: :func:`refine_latents`, which semi-amortised training runs
inside each training step, ``train/semi_amortised.py``, and :func:`learned_refine`, which the refiner's training
runs, ``train/learned_refiner.py``).
"""

from .graphs import (GRAPH_MIN_STEPS, GraphedDecoder, context_loss, perceptual_distance, step_decoder,
                     uses_cuda_graphs)
from .loop import (CPU_CHANNELS_LAST, RDOCheck, RDOResult, Refinement, annealing_temperature, decoder_fixed,
                   heads_channels_last, latent_optimiser, latent_target, learned_refine, optimise_latents, rdo_step,
                   rdo_target, refine_latents, restore_weights, start_variables)
from .loss import (CROSS_VIEW_ALPHA_FLOOR, ContextLoss, Decoded, PerceptualDistance, RDOTarget, cross_view_error,
                   decode_variables, psnr_of_mse, rdo_loss, render_context_views)
from .presets import LATENT_LIMIT, PRESETS, VARIABLES, RDOConfig, cross_view_default, preset_steps, rdo_config
from .refiner import (LatentRefiner, RefinerConfig, RefinerState, load_refiner, refiner_id, refiner_step,
                      save_refiner)

__all__ = ['CPU_CHANNELS_LAST', 'CROSS_VIEW_ALPHA_FLOOR', 'ContextLoss', 'Decoded', 'GRAPH_MIN_STEPS', 'GraphedDecoder', 'LATENT_LIMIT', 'LatentRefiner', 'PRESETS', 'PerceptualDistance', 'RDOCheck', 'RDOConfig', 'RDOResult', 'RDOTarget', 'Refinement', 'RefinerConfig', 'RefinerState', 'VARIABLES', 'annealing_temperature', 'context_loss', 'cross_view_default', 'cross_view_error', 'decode_variables', 'decoder_fixed', 'heads_channels_last', 'latent_optimiser', 'latent_target', 'learned_refine', 'load_refiner', 'optimise_latents', 'perceptual_distance', 'preset_steps', 'psnr_of_mse', 'rdo_config', 'rdo_loss', 'rdo_step', 'rdo_target', 'refine_latents', 'refiner_id', 'refiner_step', 'render_context_views', 'restore_weights', 'save_refiner', 'start_variables', 'step_decoder', 'uses_cuda_graphs']
