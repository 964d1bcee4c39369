"""The only package that touches the cffi extension ``edgemodbus._native``.

It declares nothing itself (the cdefs are in csrc/cdefs/), wraps each C call the rest
of edgemodbus needs, reads errno right after a failed call and maps it to the
exception hierarchy of :mod:`edgemodbus.errors`.

* native.py: loading the extension (or its ASan build), the source fingerprint, limits;
* errors.py: errno -> exception;
* block.py, context.py: the read buffers, a libmodbus context and the csrc/emb_io.c and
  csrc/emb_stream.c calls;
* check.py: the one reply check (csrc/emb_check.c) for bytes held in Python;
* codec.py: the C value codec (csrc/emb_codec.c);
* loop.py: the loop engine (csrc/emb_loop.c, csrc/emb_loop_link.c): many DTU streams on
  one thread (docs/scale.md);
* sourcehash.py: the fingerprint of the C sources (build_ffi.py loads it by path).

Objects here hold cdata; the other packages hold these objects, never raw cdata.
"""

from __future__ import annotations

from . import check
from .block import Block
from .codec import (
    CODEC_MODE_ALL,
    CODEC_MODE_TRACK,
    CODEC_MODE_VALUES,
    CodecItem,
    CodecLayout,
    CodecPlan,
    CodecScale,
    ScaleFactors,
    codec_constants,
    codec_encode,
)
from .context import Context, StreamCounters, discard_input
from .errors import error_from_errno
from .native import (
    MAX_ADU_LENGTH,
    MAX_HEARTBEAT,
    MAX_READ_BITS,
    MAX_READ_REGISTERS,
    MAX_WRITE_BITS,
    MAX_WRITE_REGISTERS,
    check_fingerprint,
    ffi,
    lib,
)
from .sourcehash import source_hash

__all__ = [
    "CODEC_MODE_ALL",
    "CODEC_MODE_TRACK",
    "CODEC_MODE_VALUES",
    "MAX_ADU_LENGTH",
    "MAX_HEARTBEAT",
    "MAX_READ_BITS",
    "MAX_READ_REGISTERS",
    "MAX_WRITE_BITS",
    "MAX_WRITE_REGISTERS",
    "Block",
    "CodecItem",
    "CodecLayout",
    "CodecPlan",
    "CodecScale",
    "Context",
    "ScaleFactors",
    "StreamCounters",
    "check",
    "check_fingerprint",
    "codec_constants",
    "codec_encode",
    "discard_input",
    "error_from_errno",
    "ffi",
    "lib",
    "source_hash",
]
