"""Adaptive binary range coding: the entropy coder of ``.tsd`` detail tiles.

The binary range coder of LZMA (I. Pavlov, LZMA SDK, ``lzma-specification``):
a bit is coded against an adaptive probability ``p / 2^11`` that it is 0; the
interval ``[low, low + range)`` shrinks to the bit's share, ``bound = (range >>
11) p``, and is renormalised a byte at a time once ``range < 2^24``, with a
carry cache so that output bytes never need patching. Probabilities adapt by
``p += (2^11 - p) >> SHIFT`` after a 0 and ``p -= p >> SHIFT`` after a 1, a
shift of 4 (faster than LZMA's 5) because a tile codes only a few hundred
symbols; a caller with long stationary runs passes :data:`SLOW_SHIFT` (LZMA's 5)
instead. Pure Python, standard library only: it runs in Pyodide.

A caller's model is a ``list`` of probabilities (its contexts), each entry
starting at ``HALF``; encoder and decoder must make the same calls in the same
order with the same models.
"""

from __future__ import annotations

from .errors import TesseraError

PROB_BITS = 11
HALF = 1 << (PROB_BITS - 1)
SHIFT = 4
#: the adaptation of long stationary runs, such as a control mesh's 10^4 point residuals
#: (``client_py.control_mesh``, version 6): 1.1-1.3 % fewer bytes there than :data:`SHIFT`
SLOW_SHIFT = 5
TOP = 1 << 24
MASK32 = 0xFFFFFFFF


class RangeDecodeError(TesseraError, ValueError):
    """The coded bytes end before the decoder has all its symbols."""


class RangeEncoder:
    """Collects coded bytes; call :meth:`finish` once, after the last bit."""

    def __init__(self) -> None:
        self.low = 0
        self.range = MASK32
        self._cache = 0
        self._pending = 1  # bytes waiting for a possible carry: the cache and 0xFF run
        self.out = bytearray()

    def _shift_low(self) -> None:
        low = self.low
        if low < 0xFF000000 or low > MASK32:
            carry = low >> 32
            byte = self._cache
            while self._pending:
                self.out.append((byte + carry) & 0xFF)
                byte = 0xFF
                self._pending -= 1
            self._cache = (low >> 24) & 0xFF
        self._pending += 1
        self.low = (low & 0x00FFFFFF) << 8

    def bit(self, model: list[int], context: int, bit: int, shift: int = SHIFT) -> None:
        """Code ``bit`` (0 or 1) with the adaptive probability ``model[context]``, which
        then moves ``1 / 2^shift`` of the way towards the bit."""
        p = model[context]
        width = self.range
        bound = (width >> PROB_BITS) * p
        if bit:
            self.low += bound
            width -= bound
            model[context] = p - (p >> shift)
        else:
            width = bound
            model[context] = p + (((1 << PROB_BITS) - p) >> shift)
        while width < TOP:  # _shift_low reads low alone
            width <<= 8
            self._shift_low()
        self.range = width

    def finish(self) -> bytes:
        """Flush the interval and return every coded byte (the first is always 0 and
        is left out; :class:`RangeDecoder` puts it back)."""
        for _ in range(5):
            self._shift_low()
        return bytes(self.out[1:])


class RangeDecoder:
    """Decodes the bytes of :meth:`RangeEncoder.finish`; reading past their end raises
    :class:`RangeDecodeError` (``pos`` is then the number of bytes it needed)."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0
        self.range = MASK32
        self.code = 0
        for _ in range(4):
            self.code = (self.code << 8) | self._byte()

    def _byte(self) -> int:
        if self.pos >= len(self.data):
            raise RangeDecodeError(f"coded data ends after {len(self.data)} bytes")
        b = self.data[self.pos]
        self.pos += 1
        return b

    def bit(self, model: list[int], context: int, shift: int = SHIFT) -> int:
        """The next bit, decoded with ``model[context]`` (updated as the encoder did, with
        the same ``shift``)."""
        p = model[context]
        bound = (self.range >> PROB_BITS) * p
        if self.code < bound:
            self.range = bound
            model[context] = p + (((1 << PROB_BITS) - p) >> shift)
            bit = 0
        else:
            self.code -= bound
            self.range -= bound
            model[context] = p - (p >> shift)
            bit = 1
        while self.range < TOP:
            self.range <<= 8
            self.code = ((self.code << 8) | self._byte()) & MASK32
        return bit


def encode_exp_golomb(enc: RangeEncoder, x: int, prefix: list[int], prefix_at: int,
                      suffix: list[int], suffix_at: int) -> None:
    """Code ``x >= 1`` as adaptive order-0 Exp-Golomb: ``n = bitlen(x) - 1`` ones then a
    zero (the ``t``-th with context ``prefix[prefix_at + t]``), then the ``n`` bits of
    ``x`` below its leading one, most significant first (the bit of weight ``2^t`` with
    context ``suffix[suffix_at + t]``)."""
    bit = enc.bit
    n = x.bit_length() - 1
    for t in range(n):
        bit(prefix, prefix_at + t, 1)
    bit(prefix, prefix_at + n, 0)
    for t in range(n - 1, -1, -1):
        bit(suffix, suffix_at + t, (x >> t) & 1)


def decode_exp_golomb(dec: RangeDecoder, prefix: list[int], prefix_at: int,
                      suffix: list[int], suffix_at: int, limit: int) -> int | None:
    """Inverse of :func:`encode_exp_golomb`; ``None`` when the prefix reaches ``limit``
    ones (the caller names that error)."""
    n = 0
    while dec.bit(prefix, prefix_at + n):
        n += 1
        if n >= limit:
            return None
    x = 1
    for t in range(n - 1, -1, -1):
        x = (x << 1) | dec.bit(suffix, suffix_at + t)
    return x
