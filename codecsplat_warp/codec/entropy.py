"""The discrete entropy model of the latents and the range coder (``constriction``) that uses it.

Every latent element is coded as an integer *residual symbol* ``s = round(z - m)`` under a zero-mean
discretised Gaussian of scale ``sigma`` (paper Eq. 7), where the prior's mean and scale come from the
network. Encoder and decoder must use bit-identically the same discrete model, so the network's outputs
are quantised before use:

* the mean to the grid :data:`MEAN_GRID` (``m = round(mean / MEAN_GRID) * MEAN_GRID``), so the decoded
  latent ``z^ = s + m`` is the same number on every machine;
* the log-scale to an index ``k`` of :data:`SCALE_LEVELS` log-spaced scales between :data:`SCALE_MIN` and
  :data:`SCALE_MAX`; each index owns one fixed probability table (:func:`discrete_models`).

Each table covers ``s`` in ``[-T_k, T_k]`` (``T_k = ceil(TAIL_SIGMAS * sigma_k)``) plus one *escape*
symbol. A residual outside that range is coded as the escape symbol followed by its excess magnitude
(Elias-gamma style: bit count, then the bits below the leading one in 16-bit chunks, then the sign), so any
residual up to ``T_k + 2**ESCAPE_MAX_BITS`` is coded exactly; larger ones raise InputError.

Symbols of one latent level are range coded grouped by scale index, in ascending index order, each group
in raster order: the decoder knows every index of a level before decoding it (the prior depends only on
coarser levels), so it can rebuild the groups.

The tables are computed in float64 on the CPU with ``torch.special.ndtr`` and turned into fixed-point
models by ``constriction``. A different C math library could, in principle, round one probability
differently, and another constriction version could quantise the tables differently; the digest of
:func:`entropy_model_digest` covers both (the float64 tables and the code words of a fixed message coded
with every table) and is part of the model identifier that every bitstream names
(:func:`codecsplat_warp.model.pretrained.model_id`), so such a machine refuses the bitstream with a clear
error instead of decoding garbage.
"""

from __future__ import annotations

import functools
import hashlib
import math
from dataclasses import dataclass

import constriction
import numpy as np
import torch

from ..errors import BitstreamError, InputError

SCALE_MIN = 0.11
"""Smallest prior scale (in latent units); smaller predictions are raised to it."""

SCALE_MAX = 256.0
"""Largest prior scale; larger predictions are lowered to it."""

SCALE_LEVELS = 64
"""Number of log-spaced scales in the table (adjacent scales differ by about 13 %)."""

LOG_SCALE_STEP = (math.log(SCALE_MAX) - math.log(SCALE_MIN)) / (SCALE_LEVELS - 1)
"""Spacing of the scale table in natural-log units."""

MEAN_GRID = 1.0 / 64.0
"""Prior means are rounded to multiples of this (a power of two: exact in every float format)."""

TAIL_SIGMAS = 8.0
"""Each table covers residuals within this many of its scales; larger ones are escaped."""

ESCAPE_MAX_BITS = 32
"""Escaped residuals exceed the table range by less than ``2**ESCAPE_MAX_BITS``."""

ESCAPE_CHUNK_BITS = 16
"""The escape payload is written in uniform chunks of this many bits (constriction allows up to 24)."""

LIKELIHOOD_MIN = 1e-9
"""Lower bound of a symbol's probability in the rate estimate's value (about 30 bits), close to an escape's cost."""

_categorical = constriction.stream.model.Categorical
_uniform = constriction.stream.model.Uniform


def log_scale_bounds() -> tuple[float, float]:
    """(log SCALE_MIN, log SCALE_MAX): the range the network's log-scales are clamped to."""
    return math.log(SCALE_MIN), math.log(SCALE_MAX)


def scale_table() -> torch.Tensor:
    """[SCALE_LEVELS] float64 scales ``SCALE_MIN * exp(k * LOG_SCALE_STEP)``."""
    return SCALE_MIN * torch.exp(torch.arange(SCALE_LEVELS, dtype=torch.float64) * LOG_SCALE_STEP)


def scale_index(log_scale: torch.Tensor) -> torch.Tensor:
    """Index (int64, same shape) of the table scale nearest in log space to ``exp(log_scale)``."""
    k = torch.round((log_scale - math.log(SCALE_MIN)) / LOG_SCALE_STEP)
    return k.clamp(0, SCALE_LEVELS - 1).to(torch.int64)


def quantize_mean(mean: torch.Tensor) -> torch.Tensor:
    """The prior mean rounded to the :data:`MEAN_GRID` (same dtype)."""
    return torch.round(mean / MEAN_GRID) * MEAN_GRID


def gaussian_bits(residual: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Eq. 7 per element: ``-log2 P(residual)`` under a zero-mean Gaussian of ``scale`` integrated over
    ``[residual - 0.5, residual + 0.5]`` (float32 at least), at most ``-log2(LIKELIHOOD_MIN)`` bits.

    It is computed in the log domain (``log_ndtr``, accurate far into the tails), and the bound holds only
    the value: the gradient is that of the unbounded code length, so the rate keeps pulling an outlier
    back and keeps widening its scale. (With the bound on the probability, an element past ~30 bits had
    no rate gradient at all and could drift away for good; stage 2 diverged at small lambda that way.)
    """
    dtype = torch.promote_types(residual.dtype, torch.float32)
    r, s = residual.to(dtype).abs(), scale.to(dtype)
    log_upper = torch.special.log_ndtr((0.5 - r) / s)
    log_lower = torch.special.log_ndtr((-0.5 - r) / s)
    ratio = torch.exp(log_lower - log_upper).clamp_max(1.0 - torch.finfo(dtype).eps)
    bits = -(log_upper + torch.log1p(-ratio)) / math.log(2.0)
    return bits.detach().clamp_max(-math.log2(LIKELIHOOD_MIN)) + (bits - bits.detach())


@dataclass(frozen=True)
class DiscreteModels:
    """The fixed probability tables, one per scale index.

    Attributes:
        tails: [SCALE_LEVELS] int64, T_k: table k codes residuals in [-T_k, T_k]; symbol 2*T_k+1 escapes.
        models: constriction Categorical models over {0, ..., 2*T_k+1} (residual + T_k, then the escape).
        digest: SHA-256 hex of every table's float64 probabilities and of the code words of each table's
            alphabet (every symbol once, in order) coded with it.
    """

    tails: np.ndarray
    models: tuple
    digest: str


@functools.lru_cache(maxsize=1)
def discrete_models() -> DiscreteModels:
    """The tables of :class:`DiscreteModels` (built once per process, about 20 ms)."""
    sha = hashlib.sha256()
    tails, models = [], []
    for sigma in scale_table().tolist():
        tail = math.ceil(TAIL_SIGMAS * sigma)
        values = torch.arange(-tail, tail + 1, dtype=torch.float64)
        pmf = torch.special.ndtr((values + 0.5) / sigma) - torch.special.ndtr((values - 0.5) / sigma)
        escape = (1.0 - pmf.sum()).clamp_min(0.0)
        probabilities = torch.cat([pmf, escape[None]]).numpy()
        model = _categorical(probabilities, perfect=False)
        canary = new_encoder()
        canary.encode(np.arange(len(probabilities), dtype=np.int32), model)
        sha.update(probabilities.astype("<f8").tobytes())
        sha.update(encoder_bytes(canary))
        tails.append(tail)
        models.append(model)
    return DiscreteModels(np.asarray(tails, dtype=np.int64), tuple(models), sha.hexdigest())


def entropy_model_digest() -> str:
    """SHA-256 hex of the probability tables (part of every model identifier)."""
    return discrete_models().digest


def new_encoder():
    """An empty range encoder for one feature stream."""
    return constriction.stream.queue.RangeEncoder()


def encoder_bytes(encoder) -> bytes:
    """The coded stream: the encoder's 32-bit words, little-endian."""
    return encoder.get_compressed().astype("<u4").tobytes()


def new_decoder(data: bytes):
    """A range decoder reading ``data`` (a multiple of 4 bytes, as written by :func:`encoder_bytes`)."""
    if len(data) % 4:
        raise BitstreamError(f"a feature stream must hold whole 32-bit words, got {len(data)} bytes")
    return constriction.stream.queue.RangeDecoder(np.frombuffer(data, dtype="<u4").astype(np.uint32))


def _groups(indices: np.ndarray):
    """(scale index, positions in raster order) for each distinct index, ascending."""
    order = np.argsort(indices, kind="stable")
    keys, starts = np.unique(indices[order], return_index=True)
    bounds = list(starts[1:]) + [len(order)]
    return [(int(k), order[a:b]) for k, a, b in zip(keys, starts, bounds)]


def encode_symbols(encoder, symbols: np.ndarray, indices: np.ndarray) -> None:
    """Append residual symbols (int64 [n]) with their scale indices (int64 [n], in [0, SCALE_LEVELS)).

    Raises:
        InputError: a residual exceeds its table range by ``2**ESCAPE_MAX_BITS`` or more.
    """
    tables = discrete_models()
    too_large = np.abs(symbols) > tables.tails[indices] + 2**ESCAPE_MAX_BITS
    if too_large.any():
        value = int(symbols[np.flatnonzero(too_large)[0]])
        raise InputError(f"latent residual {value} is beyond the codable range (table range + 2**{ESCAPE_MAX_BITS}); "
                         "the network produced a non-sensical feature")
    for k, positions in _groups(indices):
        tail = int(tables.tails[k])
        values = symbols[positions]
        outside = np.abs(values) > tail
        mapped = np.where(outside, 2 * tail + 1, values + tail).astype(np.int32)
        encoder.encode(mapped, tables.models[k])
        for value in values[outside].tolist():
            _encode_escape(encoder, value, tail)


def decode_symbols(decoder, indices: np.ndarray) -> np.ndarray:
    """Residual symbols int64 [n] for the scale indices ``indices`` (int64 [n]); inverse of :func:`encode_symbols`."""
    tables = discrete_models()
    symbols = np.zeros(len(indices), dtype=np.int64)
    for k, positions in _groups(indices):
        tail = int(tables.tails[k])
        mapped = decoder.decode(tables.models[k], len(positions)).astype(np.int64)
        values = mapped - tail
        for i in np.flatnonzero(mapped == 2 * tail + 1).tolist():
            values[i] = _decode_escape(decoder, tail)
        symbols[positions] = values
    return symbols


def _encode_escape(encoder, value: int, tail: int) -> None:
    excess = abs(value) - tail - 1
    bits = excess.bit_length()
    encoder.encode(bits, _uniform(ESCAPE_MAX_BITS + 1))
    remaining = bits - 1
    while remaining > 0:
        chunk = min(ESCAPE_CHUNK_BITS, remaining)
        remaining -= chunk
        encoder.encode((excess >> remaining) & ((1 << chunk) - 1), _uniform(1 << chunk))
    encoder.encode(int(value < 0), _uniform(2))


def _decode_escape(decoder, tail: int) -> int:
    bits = int(decoder.decode(_uniform(ESCAPE_MAX_BITS + 1)))
    excess = 1 if bits else 0
    remaining = bits - 1
    while remaining > 0:
        chunk = min(ESCAPE_CHUNK_BITS, remaining)
        remaining -= chunk
        excess = (excess << chunk) | int(decoder.decode(_uniform(1 << chunk)))
    magnitude = excess + tail + 1
    return -magnitude if int(decoder.decode(_uniform(2))) else magnitude
