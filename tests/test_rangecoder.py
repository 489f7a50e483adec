"""The adaptive binary range coder's Exp-Golomb codes (client_py.rangecoder): round trips of
any positive integer, the cost near ``2 log2(x)`` bits for a flat spread, and the prefix
limit reported, not decoded past."""

import math
import random

from client_py.rangecoder import (
    HALF,
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
