"""The .tsp patch format v1 (docs/format.md): round trips, the size target, the byte
layout, and that every malformed file raises PatchFormatError and nothing else."""

from __future__ import annotations

import json
import math
import struct
import zlib
from functools import cache

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from nurbs_cases import random_knots, random_surface
from scipy.interpolate import BSpline

from client_py import (
    NurbsSurface,
    PatchFormatError,
    TrimMask,
    read_patch,
    uniform_clamped_knots,
    write_patch,
)
from client_py.format import HEADER, HEADER_SIZE, MAGIC

FUZZ = settings(max_examples=120, deadline=2000, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow])


def small_patch() -> NurbsSurface:
    """Rational, non-uniform knots in u, uniform in v, a trim mask and metadata."""
    rng = np.random.default_rng(1)
    U = random_knots(rng, 6, 2, (0.0, 2.0))
    V = uniform_clamped_knots(5, 1)
    P = rng.uniform(-50, 50, (6, 5, 3))
    W = rng.uniform(0.5, 2.0, (6, 5))
    trim = TrimMask([[1, 1, 0], [0, 1, 1]])
    return NurbsSurface((2, 1), (U, V), P, W, trim=trim, metadata={"units": "mm", "n": 3})


@cache
def small_file() -> bytes:
    return write_patch(small_patch())


def axis_errors(a: NurbsSurface, b: NurbsSurface) -> np.ndarray:
    """Per-axis max |P_a - P_b| divided by the extent of P_a on that axis."""
    pa, pb = np.array(a.control_points), np.array(b.control_points)
    extent = np.ptp(pa.reshape(-1, 3), axis=0)
    return np.abs(pa - pb).reshape(-1, 3).max(axis=0) / extent


# ------------------------------------------------------------------ round trips
def test_round_trip_keeps_everything():
    s = small_patch()
    data = write_patch(s, metadata={"title": "test", "units": "cm"})
    r = read_patch(data)
    assert r.degree == s.degree and r.shape == s.shape
    assert r.knots == s.knots  # non-uniform knots are stored as float64: exact
    assert r.trim == s.trim
    assert r.metadata == {"units": "cm", "n": 3, "title": "test"}  # the argument wins
    assert axis_errors(s, r).max() <= 2.0**-16
    lw, lr = np.log(np.array(s.weights)), np.log(np.array(r.weights))
    assert np.abs(lw - lr).max() <= np.ptp(lw) / (2 * (2**16 - 1)) * (1 + 1e-9)
    assert write_patch(s, metadata={"title": "test", "units": "cm"}) == data  # deterministic


@pytest.mark.parametrize("bits", [2, 5, 8, 12, 16, 20, 24, 30])
def test_quantisation_error_is_half_a_step(bits):
    s = random_surface(np.random.default_rng(bits), 3, 2, 9, 8)
    r = read_patch(write_patch(s, bits=bits))
    half_step = 1.0 / (2 * (2**bits - 1))
    assert axis_errors(s, r).max() <= half_step * (1 + 1e-9) + 1e-15
    assert r.knots == s.knots


def test_uniform_knots_are_a_flag_and_exact():
    U = uniform_clamped_knots(23, 3, -1.5, 7.25)
    V = uniform_clamped_knots(11, 2)
    P = np.random.default_rng(2).normal(size=(23, 11, 3))
    s = NurbsSurface((3, 2), (U, V), P)
    data = write_patch(s)
    flags = struct.unpack_from("<H", data, 6)[0]
    assert flags == 4 | 8  # uniform U, uniform V; not rational, no trim
    r = read_patch(data)
    assert r.knots == s.knots and not r.is_rational and r.trim is None
    s2 = NurbsSurface((3, 2), (U[:10] + [U[10] + 1e-9] + U[11:], V), P)
    assert struct.unpack_from("<H", write_patch(s2), 6)[0] == 8
    assert read_patch(write_patch(s2)).knots == s2.knots


def test_header_layout_matches_the_spec():
    data = small_file()
    magic, version, flags, p, q, n_u, n_v, bits, reserved, size, raw = struct.unpack_from(
        "<4sHHBBHHBBII", data)
    assert (magic, version, p, q, n_u, n_v, bits, reserved) == (b"TSPF", 1, 2, 1, 6, 5, 16, 0)
    assert flags == 1 | 2 | 8  # rational, trim, uniform V
    assert len(data) == 24 + size + 4
    assert struct.unpack_from("<I", data, 24 + size)[0] == zlib.crc32(data[: 24 + size])
    payload = zlib.decompress(data[24 : 24 + size])
    assert len(payload) == raw
    # payload starts with the domain, then U's interior knots (V is uniform)
    assert struct.unpack_from("<4d", payload) == (0.0, 2.0, 0.0, 1.0)
    assert struct.unpack_from("<3d", payload, 32) == small_patch().knots[0][3:6]
    meta = json.dumps({"n": 3, "units": "mm"}, separators=(",", ":")).encode()
    assert payload.endswith(struct.pack("<I", len(meta)) + meta)


@cache
def relief_patch() -> NurbsSurface:
    """A realistic smooth-but-detailed patch: the example relief (fitter.fitting.examples: rosette,
    groove, sharp step, convex face; 200 x 140 mm) as a 40 x 40 degree-2 height field,
    least-squares fitted to 12,000 scattered points with 0.05 mm noise (control x, y at
    the Greville abscissae, z fitted), with smooth weights 1 + 0.2 sin cos plus 1e-3 noise,
    as a nonlinear refinement leaves them."""
    from fitter.fitting.examples import relief_height

    n, p, count = 40, 2, 12_000
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-100, 100, count), rng.uniform(-70, 70, count)
    z = relief_height(x, y) + rng.normal(0, 0.05, count)
    U = np.array(uniform_clamped_knots(n, p, -100, 100))
    V = np.array(uniform_clamped_knots(n, p, -70, 70))
    Bu = BSpline.design_matrix(x, U, p).toarray()
    Bv = BSpline.design_matrix(y, V, p).toarray()
    A = sp.csr_matrix(np.einsum("ka,kb->kab", Bu, Bv).reshape(count, -1))
    coef = np.linalg.solve((A.T @ A).toarray() + 1e-6 * np.eye(n * n), A.T @ z)
    gu = np.array([U[i + 1 : i + p + 1].mean() for i in range(n)])
    gv = np.array([V[i + 1 : i + p + 1].mean() for i in range(n)])
    X, Y = np.meshgrid(gu, gv, indexing="ij")
    W = 1 + 0.2 * np.sin(3 * X / 100) * np.cos(2 * Y / 70) + rng.normal(0, 1e-3, X.shape)
    transform = [[0.8, -0.6, 0, 250.0], [0.6, 0.8, 0, -40.0], [0, 0, 1, 1200.0], [0, 0, 0, 1]]
    knots = uniform_clamped_knots(n, p)
    return NurbsSurface((p, p), (knots, knots), np.stack([X, Y, coef.reshape(n, n)], -1), W,
                        metadata={"units": "mm", "transform": transform, "title": "relief"})


def test_size_target_40x40_rational_at_16_bits():
    s = relief_patch()
    data = write_patch(s, bits=16)
    print(f"\n40x40 degree-2 rational relief patch: {len(data)} bytes at 16 bits "
          f"(float64 control points and weights: {40 * 40 * 4 * 8} bytes)")
    assert len(data) <= 8 * 1024
    r = read_patch(data)
    assert axis_errors(s, r).max() <= 2.0**-16
    # on the surface: the deviation stays at the quantisation scale (z extent ~ 12 mm)
    ts = np.linspace(0, 1, 23)
    dev = max(abs(a - b) for u in ts for v in ts
              for a, b in zip(s.evaluate(u, v), r.evaluate(u, v), strict=True))
    assert dev <= 2.0**-16 * 200 * 2


# ------------------------------------------------------------------ specific errors
def reframe(payload: bytes, **fields) -> bytes:
    """A file around a raw payload with valid sizes and CRC; header ``fields`` overridden."""
    head = dict(zip(["magic", "version", "flags", "p", "q", "n_u", "n_v", "bits", "reserved",
                     "size", "raw"], HEADER.unpack_from(small_file()), strict=True))
    blob = zlib.compress(payload, 9)
    head.update(size=len(blob), raw=len(payload))
    head.update(fields)
    if "blob" in fields:
        blob = head.pop("blob")
    body = HEADER.pack(*[v for k, v in head.items() if k != "blob"]) + blob
    return body + struct.pack("<I", zlib.crc32(body))


def payload_of(data: bytes) -> bytes:
    return zlib.decompress(data[HEADER_SIZE:-4])


def with_metadata(text: bytes) -> bytes:
    raw = payload_of(small_file())
    (meta_len,) = struct.unpack_from("<I", raw, len(raw) - len(small_patch_meta()) - 4)
    return reframe(raw[: len(raw) - meta_len - 4] + struct.pack("<I", len(text)) + text)


def small_patch_meta() -> bytes:
    return json.dumps(small_patch().metadata, sort_keys=True, separators=(",", ":")).encode()


def test_reframe_of_the_same_payload_reads():
    assert read_patch(reframe(payload_of(small_file()))).knots == small_patch().knots


def flip(data: bytes, offset: int) -> bytes:
    return data[:offset] + bytes([data[offset] ^ 0x10]) + data[offset + 1 :]


def corrupt_cases():
    data = small_file()
    raw = payload_of(data)
    meta_len = len(small_patch_meta())
    meta_at = len(raw) - meta_len - 4
    return [
        ("abc", 0, "expected bytes, got str"),
        (b"PK\x03\x04" + data[4:], 0, "not a Tessera patch"),
        (b"", 0, "not a Tessera patch"),
        (data[:12], 12, "truncated: 12 bytes, the header alone needs 28"),
        (data[:-5], len(data) - 5, f"truncated: {len(data) - 5} bytes of {len(data)}"),
        (data + b"\0", len(data), "1 unexpected trailing bytes"),
        (flip(data, 40), len(data) - 4, "CRC32 mismatch"),
        (reframe(raw, version=2), 4, "format version 2 is not supported"),
        (reframe(raw, flags=0x40), 6, "unknown flags 0x0040"),
        (reframe(raw, p=0), 8, "degree p = 0 outside 1..15"),
        (reframe(raw, n_v=1), 12, "n_v = 1 control points < degree"),
        (reframe(raw, n_u=65535, n_v=65535), 10, "n_u = 65535 control points > 1024 per side"),
        (reframe(raw, n_u=1024, n_v=257), 10, "grid 1024x257 exceeds 262144 control points"),
        (reframe(raw, bits=31), 14, "bits = 31 outside 2..30"),
        (reframe(raw, reserved=7), 15, "reserved byte is 7"),
        (reframe(raw, raw=10**9), 20, "exceeds the"),
        (reframe(raw, raw=len(raw) - 1), 20, "payload inflates to more than"),
        (reframe(raw, raw=len(raw) + 1), 20, f"payload inflates to {len(raw)} bytes"),
        (reframe(raw, blob=b"not zlib at all", size=15), HEADER_SIZE, "does not decompress"),
        (reframe(raw, blob=zlib.compress(raw)[:-2], size=len(zlib.compress(raw)) - 2),
         None, "ends early"),
        (reframe(raw, blob=zlib.compress(raw) + b"xx", size=len(zlib.compress(raw)) + 2),
         None, "2 bytes after the compressed payload"),
        (reframe(raw[:40]), 20, "payload size 40 is below the 491 bytes a 6x5 grid needs"),
        (reframe(raw[:meta_at] + struct.pack("<I", meta_len + 16) + raw[meta_at + 4 :]),
         None, f"metadata needs {meta_len + 16} bytes, {meta_len} remain"),
        (reframe(raw + b"\0\0"), None, "2 bytes left after metadata"),
        (reframe(raw[:32] + struct.pack("<d", math.nan) + raw[40:]), 32, "knots U holds a non-"),
        (reframe(raw[:32] + struct.pack("<3d", 1.5, 0.5, 1.0) + raw[56:]), HEADER_SIZE,
         "decoded surface is invalid.*decreases"),
        (with_metadata(b"{not json"), None, "metadata is not UTF-8 JSON"),
        (with_metadata(b"\xff\xfe"), None, "metadata is not UTF-8 JSON"),
        (with_metadata(b"[1, 2]"), None, "metadata JSON is not an object"),
        (with_metadata(b'{"a": NaN}'), None, "NaN is not JSON"),
        (with_metadata(b'{"a": 1e999}'), None, "overflows a double"),
        (with_metadata(b'{"a": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"), None,
         "metadata is not UTF-8 JSON"),
        (with_metadata(b'{"a": ' + b"9" * 5000 + b"}"), None, "metadata is not UTF-8 JSON"),
        (with_metadata(b'{"a": "' + b"x" * (1 << 20) + b'"}'), None,
         "metadata length 1048585 exceeds 1 MiB"),
    ]


@pytest.mark.parametrize("case", range(len(corrupt_cases())))
def test_corrupt_file_raises_patch_format_error(case):
    data, offset, match = corrupt_cases()[case]
    with pytest.raises(PatchFormatError, match=match) as info:
        read_patch(data)
    err = info.value
    assert isinstance(err, ValueError) and err.reason in str(err)
    if offset is not None:
        assert err.offset == offset


def test_write_patch_rejects_bad_arguments():
    s = small_patch()
    with pytest.raises(ValueError, match="bits must be an integer in 2..30, got 31"):
        write_patch(s, bits=31)
    with pytest.raises(ValueError, match="bits must be an integer"):
        write_patch(s, bits=True)
    with pytest.raises(ValueError, match="surface must be a NurbsSurface, got dict"):
        write_patch({})
    with pytest.raises(ValueError, match="metadata must be JSON-serialisable"):
        write_patch(s, metadata={"a": object()})
    with pytest.raises(ValueError, match="metadata must be JSON-serialisable"):
        write_patch(s, metadata={"a": math.inf})


# ------------------------------------------------------------------ fuzzing
def read_or_format_error(data: bytes) -> NurbsSurface | None:
    """``read_patch`` may succeed or raise PatchFormatError; any other exception fails."""
    try:
        return read_patch(data)
    except PatchFormatError:
        return None


@FUZZ
@given(st.data())
def test_truncation_is_detected(data):
    file = small_file()
    cut = data.draw(st.integers(0, len(file) - 1))
    with pytest.raises(PatchFormatError):
        read_patch(file[:cut])


@FUZZ
@given(st.lists(st.integers(0, 8 * len(small_file()) - 1), min_size=1, max_size=8, unique=True))
def test_bit_flips_are_detected(bits):
    data = bytearray(small_file())
    for bit in bits:
        data[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(PatchFormatError):
        read_patch(bytes(data))


@FUZZ
@given(st.binary(max_size=400))
def test_random_bytes_are_rejected(blob):
    for data in (blob, MAGIC + blob, small_file()[:HEADER_SIZE] + blob):
        with pytest.raises(PatchFormatError):
            read_patch(data)


@FUZZ
@given(st.binary(min_size=HEADER_SIZE - 6, max_size=HEADER_SIZE - 6))
def test_random_header_with_valid_crc(head):
    """Past the CRC: any header fields over a valid payload decode or fail cleanly."""
    body = MAGIC + b"\x01\x00" + head + small_file()[HEADER_SIZE:-4]
    read_or_format_error(body + struct.pack("<I", zlib.crc32(body)))


@FUZZ
@given(st.data())
def test_corrupt_payload_with_valid_crc(data):
    """The decoder itself (behind a correct CRC): byte edits of the decompressed payload,
    recompressed and reframed, decode to some surface or raise PatchFormatError."""
    raw = bytearray(payload_of(small_file()))
    for _ in range(data.draw(st.integers(1, 4))):
        kind = data.draw(st.sampled_from(["set", "cut", "insert"]))
        at = data.draw(st.integers(0, len(raw)))
        if kind == "set" and at < len(raw):
            raw[at] = data.draw(st.integers(0, 255))
        elif kind == "cut":
            del raw[at : at + data.draw(st.integers(1, 16))]
        else:
            raw[at:at] = data.draw(st.binary(min_size=1, max_size=16))
    result = read_or_format_error(reframe(bytes(raw)))
    assert result is None or isinstance(result, NurbsSurface)


def test_format_error_pickles():
    import pickle

    err = pickle.loads(pickle.dumps(PatchFormatError(12, "bad thing", "payload")))
    assert (err.offset, err.reason, err.section) == (12, "bad thing", "payload")
    assert str(err) == "invalid Tessera patch at payload byte 12: bad thing"
