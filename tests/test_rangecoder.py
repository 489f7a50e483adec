"""The adaptive binary range coder's Exp-Golomb codes (client_py.rangecoder): round trips of
any positive integer, the cost near ``2 log2(x)`` bits for a flat spread, and the prefix
limit reported, not decoded past."""

import math
import random

from client_py.rangecoder import (
    HALF,
    SLOW_SHIFT,
    RangeDecoder,
    RangeEncoder,
    decode_exp_golomb,
    encode_exp_golomb,
)


def test_exp_golomb_round_trip_and_cost():
    rnd = random.Random(3)
    values = [1, 2, 3, 255, 256, (1 << 28) - 1] + [rnd.randint(1, 1000) for _ in range(2000)]
    enc = RangeEncoder()
    prefix, suffix = [HALF] * 40, [HALF] * 40
    for x in values:
        encode_exp_golomb(enc, x, prefix, 5, suffix, 3)
    data = enc.finish()
    dec = RangeDecoder(data)
    prefix, suffix = [HALF] * 40, [HALF] * 40
    assert [decode_exp_golomb(dec, prefix, 5, suffix, 3, 31) for _ in values] == values
    ideal = sum(2 * math.floor(math.log2(x)) + 1 for x in values) / 8  # the static code
    assert len(data) < 1.02 * ideal  # adaptive contexts cost no more than the static code


def test_exp_golomb_prefix_limit():
    enc = RangeEncoder()
    encode_exp_golomb(enc, 1 << 20, [HALF] * 40, 0, [HALF] * 40, 0)
    dec = RangeDecoder(enc.finish())
    assert decode_exp_golomb(dec, [HALF] * 40, 0, [HALF] * 40, 0, 20) is None


class _ReferenceEncoder:
    """The LZMA SDK's range encoder (``lzma-specification``: ``RangeEnc_EncodeBit``,
    ``RangeEnc_ShiftLow``) written out plainly, with this coder's shift of 4."""

    def __init__(self, shift=4):
        self.low, self.range, self.cache, self.cache_size = 0, 0xFFFFFFFF, 0, 1
        self.shift = shift
        self.out = bytearray()

    def shift_low(self):
        if self.low < 0xFF000000 or self.low >= 1 << 32:
            temp = self.cache
            while True:
                self.out.append((temp + (self.low >> 32)) & 0xFF)
                temp = 0xFF
                self.cache_size -= 1
                if self.cache_size == 0:
                    break
            self.cache = (self.low >> 24) & 0xFF
        self.cache_size += 1
        self.low = (self.low & 0x00FFFFFF) << 8

    def encode(self, probs, i, bit):
        bound = (self.range >> 11) * probs[i]
        if bit == 0:
            self.range = bound
            probs[i] += (2048 - probs[i]) >> self.shift
        else:
            self.low += bound
            self.range -= bound
            probs[i] -= probs[i] >> self.shift
        while self.range < 1 << 24:
            self.range <<= 8
            self.shift_low()

    def finish(self):
        for _ in range(5):
            self.shift_low()
        return bytes(self.out[1:])


def test_the_encoder_writes_the_reference_coders_bytes():
    """Skewed and even bits in a few contexts, long runs of one bit (carries through runs
    of 0xFF bytes): byte for byte the plain reference's output."""
    rnd = random.Random(7)
    bits = ([rnd.random() < 0.03 for _ in range(20000)] + [1] * 3000
            + [rnd.random() < 0.5 for _ in range(20000)] + [0] * 3000)
    contexts = [rnd.randrange(3) for _ in bits]
    enc, ref = RangeEncoder(), _ReferenceEncoder()
    mine, theirs = [HALF] * 3, [HALF] * 3
    for bit, c in zip(bits, contexts, strict=True):
        enc.bit(mine, c, int(bit))
        ref.encode(theirs, c, int(bit))
    assert enc.finish() == ref.finish()
    assert mine == theirs


def test_the_slow_shift_is_the_reference_coders_at_lzmas_shift_and_decodes():
    """``shift=SLOW_SHIFT`` (LZMA's own 5, the control mesh's points): the reference's bytes
    and probabilities at that shift, and decoded back with the same shift."""
    rnd = random.Random(8)
    bits = [int(rnd.random() < 0.2) for _ in range(20000)] + [1] * 3000
    contexts = [rnd.randrange(2) for _ in bits]
    enc, ref = RangeEncoder(), _ReferenceEncoder(SLOW_SHIFT)
    mine, theirs = [HALF] * 2, [HALF] * 2
    for bit, c in zip(bits, contexts, strict=True):
        enc.bit(mine, c, bit, SLOW_SHIFT)
        ref.encode(theirs, c, bit)
    data = enc.finish()
    assert data == ref.finish() and mine == theirs
    dec, model = RangeDecoder(data), [HALF] * 2
    assert [dec.bit(model, c, SLOW_SHIFT) for c in contexts] == bits and model == mine
