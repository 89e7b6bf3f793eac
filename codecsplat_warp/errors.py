"""Typed exceptions of codecsplat-warp.

Every error a user can cause derives from :class:`CodecSplatError`, so callers can catch the whole
family; each subclass also derives from the closest built-in (``ValueError``, ``MemoryError``) so code
that already catches those keeps working.
"""

from __future__ import annotations


class CodecSplatError(Exception):
    """Base class of every error raised on purpose by this package."""


class InputError(CodecSplatError, ValueError):
    """A tensor argument has the wrong shape, dtype, device, layout or non-finite values.

    The message names the argument (``"depth"``, ``"feat"``, ...) and what was expected.
    """


class DeviceMismatchError(InputError):
    """Tensor arguments of one call live on different devices."""


class CameraError(InputError):
    """Camera parameters are invalid (non-finite, non-orthonormal rotation, focal <= 0, bad near/far).

    The message names the offending view index.
    """


class DataError(CodecSplatError):
    """A scene on disk cannot be read: missing file, count mismatch, bad pose, unsupported format."""


class RefinerError(DataError):
    """A learned latent refiner file cannot be used: missing, unreadable, of another format, corrupt, or trained
    for another model than the one it is given to (the message names both model ids)."""


class BitstreamError(CodecSplatError):
    """A scene bitstream is truncated, corrupt, foreign or of a newer format version."""


class RasterMemoryError(CodecSplatError, MemoryError):
    """Rasterization would need more intersection buffer memory than the configured budget."""


class MVSError(CodecSplatError, ValueError):
    """A scene cannot give multi-view stereo depth: fewer than 3 views, or a view without a usable source view
    (none overlaps it with a useful baseline). The message names the view."""


class ShardError(RuntimeError):
    """A worker process of :func:`codecsplat_warp.eval.shards.run_sharded` failed other than with one of this
    package's errors (which keep their type): an exception that is not a :class:`CodecSplatError` (a bug: the
    message holds the worker's traceback), a crash, or a worker killed from outside. The message names the shard
    and its device. Deliberately not a :class:`CodecSplatError`: the command line reports it as an internal error."""


class NoSamplesError(DataError):
    """An evaluation finds no sample to score: every scene is unusable with its protocol, or its index selects
    none. ``skipped`` lists the unusable scenes as ``{"scene": name, "reason": text}``."""

    def __init__(self, message: str, skipped: list[dict] | None = None):
        super().__init__(message)
        self.skipped = list(skipped or [])


class ViewerError(CodecSplatError):
    """``codecsplat view`` cannot serve its input as asked: an option that does not apply to the input (``--lambda``
    with a bitstream, ``--cameras`` with a scene folder) or an address it cannot listen on. The message names the
    option."""


class PortInUseError(ViewerError):
    """The viewer's port is taken by another program. The message names the port and the way out (``--port 0``:
    the next free port)."""
