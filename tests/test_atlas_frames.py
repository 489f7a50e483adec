"""The atlas file ``.tsa`` v4 (docs/format.md, "Local frames (version 4)"): edge and patch
interior points as integer codes in a frame made from the decoded layout vertices. Round
trips within half a step along each frame axis (the frames rebuilt here in numpy from the
spec), vertices as version 3, frames orthonormal for degenerate patches too, the decoded
atlas a fixed point of the writer, fewer bytes for a coarser tangential step, bad factors
refused, every malformed file a PatchFormatError; and the fitter's rounding in the frames
(``fit.frame_fed_back``): the file holds its points exactly, nearer the working points
than nearest rounding."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from atlas_cases import random_atlas, sphere_atlas
from hypothesis import given
from hypothesis import strategies as st
from test_atlas import random_cube_atlas
from test_atlas_format import FUZZ, frame_cube_file

from client_py.atlas import AtlasSurface
from client_py.atlas_format import (
    HEADER,
    HEADER_SIZE,
    canonical_atlas,
    point_frames,
    read_atlas,
    read_atlas_header,
    write_atlas,
)
from client_py.errors import PatchFormatError


def cube_file() -> bytes:
    return frame_cube_file()


def _points(atlas: AtlasSurface) -> np.ndarray:
    return np.array([*atlas.vertices, *atlas.edge_points, *atlas.face_points])


def _numpy_frames(atlas: AtlasSurface) -> np.ndarray:
    """Per edge and interior point its frame rows ``(n, t1, t2)``, from the spec: a patch's
    normal the unit cross product of its diagonals, an edge's the sum of its patches'; the
    direction along an edge ``hi - lo``, along a patch ``(b - a) + (c - d)``; Gram-Schmidt
    (none of these cases is degenerate)."""
    v = np.array(atlas.vertices)
    q = np.array(atlas.quads)
    n = np.cross(v[q[:, 2]] - v[q[:, 0]], v[q[:, 3]] - v[q[:, 1]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)

    def frame(normal, along):
        normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)
        t = along - np.sum(along * normal, axis=1, keepdims=True) * normal
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        return np.stack([normal, t, np.cross(normal, t)], axis=1)

    table = atlas.edges
    edge_n = np.array([sum(n[f] for f, _ in pairs) for pairs in table.faces])
    ends = np.array(table.edges)
    edges = frame(edge_n, v[ends[:, 1]] - v[ends[:, 0]])
    faces = frame(n, v[q[:, 1]] - v[q[:, 0]] + v[q[:, 2]] - v[q[:, 3]])
    inner = atlas.side - 2
    return np.concatenate([np.repeat(edges, inner, axis=0), np.repeat(faces, inner ** 2,
                                                                      axis=0)])


@pytest.mark.parametrize("make", [
    lambda: random_cube_atlas(3, 2), lambda: random_cube_atlas(2, 1),
    lambda: sphere_atlas(3, 2, 3), lambda: sphere_atlas(2, 3, 1, noise=1e-3),
    lambda: random_atlas(2, 3, 2, rational=True),
])
@pytest.mark.parametrize(("bits", "factor"), [(8, 1.0), (10, 2.0), (12, 3.25), (16, 8.0)])
def test_round_trip_within_half_a_step_along_each_frame_axis(make, bits, factor):
    atlas = canonical_atlas(make())
    data = write_atlas(atlas, bits, {"n": 1}, tangent_factor=factor)
    head = read_atlas_header(data)
    assert (head["version"], head["tangent_factor"]) == (4, factor)
    back, meta = read_atlas(data)
    assert meta == {"n": 1}
    assert back.quads == atlas.quads
    before, after = _points(atlas), _points(back)
    n_v = len(atlas.vertices)
    top = (1 << bits) - 1
    lo, hi = before[:n_v].min(axis=0), before[:n_v].max(axis=0)
    step = (hi - lo) / top
    # the vertices: version 3's grid over the vertices' bounds
    assert np.array_equal(after[:n_v], lo + np.rint((before[:n_v] - lo) / step) * step)
    # the rest: within half a step along each axis of the frame made from those vertices
    frames = _numpy_frames(back)
    along = np.einsum("kjc,kc->kj", frames, before[n_v:] - after[n_v:])
    s = step.mean()
    half = np.array([s, factor * s, factor * s]) / 2
    assert np.all(np.abs(along) <= half * (1 + 1e-9))
    assert np.abs(along[:, 0]).max() > 0.3 * half[0]  # the normal step is used, not finer
    if atlas.weights is not None:
        assert np.allclose(back.weights, atlas.weights, rtol=1e-2)


def test_the_decoded_atlas_is_a_fixed_point_of_the_writer():
    atlas = sphere_atlas(3, 3, 1, noise=1e-3)
    back, meta = read_atlas(write_atlas(atlas, 9, tangent_factor=2))
    again, _ = read_atlas(write_atlas(back, 9, meta, tangent_factor=2))
    np.testing.assert_allclose(_points(again), _points(back), rtol=0, atol=1e-12)


def test_a_coarser_tangential_step_costs_fewer_bytes_and_version_3_still_writes():
    atlas = sphere_atlas(6, 3, 1, noise=1e-3)
    sizes = [len(write_atlas(atlas, 10, tangent_factor=k)) for k in (1, 2, 4)]
    assert sizes[0] > sizes[1] > sizes[2]
    assert read_atlas_header(write_atlas(atlas, 10, tangent_factor=None))["version"] == 3


def test_frames_are_orthonormal_where_a_patch_or_an_edge_degenerates():
    """A patch whose corners are one point, an edge along its normal: the frame falls back
    to the axes and stays orthonormal, so the codes still name every offset."""
    atlas = random_cube_atlas(3, 2)
    vertices = [list(p) for p in atlas.vertices]
    a, b, c, d = atlas.quads[0]
    for k in (b, c, d):
        vertices[k] = list(vertices[a])
    edge_frames, face_frames = point_frames(vertices, atlas.quads, atlas.edges)
    for frame in [*edge_frames, *face_frames]:
        m = np.array(frame).reshape(3, 3)
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(m) > 0
    assert face_frames[0] == (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    assert point_frames([[0, 0, 0]] * 4, [(0, 1, 2, 3)], _edges([(0, 1, 2, 3)]))[1][0] \
        == face_frames[0]


def _edges(quads):
    from client_py.atlas import atlas_edges

    return atlas_edges(quads)


def test_degenerate_patches_round_trip():
    atlas = random_cube_atlas(3, 2)
    vertices = list(atlas.vertices)
    a, b, c, d = atlas.quads[0]
    vertices[b] = vertices[c] = vertices[d] = vertices[a]
    flat = AtlasSurface(atlas.degree, atlas.spans, vertices, atlas.quads, atlas.edge_points,
                        atlas.face_points)
    back, _ = read_atlas(write_atlas(flat, 12, tangent_factor=1))
    assert np.abs(_points(back) - _points(canonical_atlas(flat))).max() < 1e-2


@pytest.mark.parametrize("factor", [0, 0.5, 0.8, 1.1, 64, "2", True, float("nan")])
def test_bad_factors_are_refused(factor):
    with pytest.raises(ValueError, match="tangent_factor"):
        write_atlas(random_cube_atlas(), 10, tangent_factor=factor)


def _with_header(data: bytes, **fields) -> bytes:
    values = list(HEADER.unpack_from(data))
    for name, value in fields.items():
        values[{"version": 1, "reserved": 6}[name]] = value
    body = HEADER.pack(*values) + data[HEADER_SIZE:-4]
    return body + struct.pack("<I", zlib.crc32(body))


def test_the_factor_byte_is_checked_and_version_3_keeps_its_reserved_byte():
    with pytest.raises(PatchFormatError, match="tangential factor 3/4 is below 1"):
        read_atlas(_with_header(cube_file(), reserved=3))
    v3 = write_atlas(random_cube_atlas(), 12)
    with pytest.raises(PatchFormatError, match="reserved byte"):
        read_atlas(_with_header(v3, reserved=8))
    # the same codes read with another factor: another atlas, no error
    other, _ = read_atlas(_with_header(cube_file(), reserved=255))
    assert np.abs(_points(other) - _points(read_atlas(cube_file())[0])).max() > 0


# ------------------------------------------------------------------ fuzzing
# (truncation and bit flips of this file: tests/test_atlas_format.py, frame_cube_file)
def _read_or_none(data: bytes):
    try:
        return read_atlas(data)
    except PatchFormatError:
        return None


@FUZZ
@given(st.binary(min_size=1, max_size=64), st.integers(0, 10 ** 6))
def test_corrupt_coded_stream_with_valid_crc(blob, at):
    """Bytes of the range-coded stream replaced (the CRC fixed): an atlas of finite points
    or a PatchFormatError, nothing else."""
    data = cube_file()
    start = HEADER_SIZE + HEADER.unpack_from(data)[9]
    body = bytearray(data[:-4])
    at = start + at % (len(body) - start)
    body[at:at + len(blob)] = blob
    result = _read_or_none(bytes(body) + struct.pack("<I", zlib.crc32(bytes(body))))
    if result is not None:
        assert np.all(np.isfinite(_points(result[0])))


@FUZZ
@given(st.binary(min_size=HEADER_SIZE - 6, max_size=HEADER_SIZE - 6))
def test_random_header_with_valid_crc(head):
    body = b"TSPA\x04\x00" + head + cube_file()[HEADER_SIZE:-4]
    _read_or_none(body + struct.pack("<I", zlib.crc32(body)))


# ------------------------------------------------------------------ the fitter's rounding
def _sphere_rounding_case(monkeypatch):
    """The sphere's 40-triangle layout fitted to 3,000 working points, version 4 written
    (``BASE_TANGENT_FACTOR`` 2): ``layout, points, atlas, f, u, v``."""
    from test_atlas_rounding import _sphere_scan

    from fitter.fitting.atlas import fit as atlas_fit
    from fitter.fitting.atlas.fit import fit_layout, working_points
    from fitter.fitting.atlas.layout import decimate, quad_layout
    from fitter.fitting.atlas.surface import scan_surface

    scan = _sphere_scan()
    surface = scan_surface(scan)
    layout = quad_layout(*decimate(surface, 40))
    points, normals = working_points(scan, surface, 3000)
    atlas, f, u, v, _ = fit_layout(layout, points, normals, rounds=3)
    monkeypatch.setattr(atlas_fit, "BASE_TANGENT_FACTOR", 2.0)
    return layout, points, atlas, f, u, v


def test_the_fitters_rounding_in_frames_is_what_the_file_holds_and_nearer(monkeypatch):
    """``fed_back_atlas`` with version 4 written (``frame_fed_back``): the file holds
    exactly its control points, and the working points lie nearer the surface drawn from
    them than from the file of the fit rounded to nearest in the same frames (the sphere
    at 8 bits, factor 2; distances to a fine drawing)."""
    from fitter.fitting.atlas.fit import fed_back_atlas, grid_mesh
    from fitter.fitting.atlas.measure import point_mesh_distance
    from fitter.fitting.atlas.patches import control_points, index_table

    layout, points, atlas, f, u, v = _sphere_rounding_case(monkeypatch)
    bits = 8
    rounded = fed_back_atlas(atlas, bits, layout, points, f, u, v, smoothing=0.1,
                             anchor=1e-3)
    decoded, _ = read_atlas(write_atlas(rounded, bits, tangent_factor=2.0))
    np.testing.assert_allclose(control_points(decoded)[index_table(decoded)],
                               control_points(rounded)[index_table(rounded)], rtol=0,
                               atol=1e-12)
    plain, _ = read_atlas(write_atlas(atlas, bits, tangent_factor=2.0))

    def rms(a):
        return float(np.sqrt(np.mean(point_mesh_distance(points, *grid_mesh(a, 17)) ** 2)))

    fit, fed, near = rms(atlas), rms(rounded), rms(plain)
    assert fed < near
    assert fed ** 2 - fit ** 2 < 0.75 * (near ** 2 - fit ** 2)


def test_the_pleat_guard_stops_after_its_passes_with_the_atlas_as_it_was(monkeypatch):
    """``frame_fed_back`` against a base whose codes pleat one more patch at every pass
    (``pleated_patches`` made so): it runs :data:`PLEAT_PASSES` passes, not one per patch
    (the sphere's 120), and returns the atlas as it was (the writer's nearest codes)."""
    from fitter.fitting.atlas import fit as atlas_fit
    from fitter.fitting.atlas.fit import PLEAT_PASSES, fed_back_atlas
    from fitter.fitting.atlas.patches import control_points

    layout, points, atlas, f, u, v = _sphere_rounding_case(monkeypatch)
    assert len(atlas.quads) > 2 * PLEAT_PASSES
    calls = []

    def one_more_each_pass(table, *_):
        pleated = np.zeros(len(table), bool)
        pleated[:len(calls)] = True  # the first call (the nearest codes): none
        calls.append(1)
        return pleated

    monkeypatch.setattr(atlas_fit, "pleated_patches", one_more_each_pass)
    rounded = fed_back_atlas(atlas, 8, layout, points, f, u, v, smoothing=0.1, anchor=1e-3)
    assert len(calls) == 1 + PLEAT_PASSES
    assert rounded is atlas
    calls.clear()
    monkeypatch.setattr(atlas_fit, "pleated_patches",
                        lambda table, *_: np.zeros(len(table), bool))
    fed = fed_back_atlas(atlas, 8, layout, points, f, u, v, smoothing=0.1, anchor=1e-3)
    assert fed is not atlas and not np.array_equal(control_points(fed), control_points(atlas))


def test_thirty_bit_frame_codes_far_from_their_prediction_round_trip():
    """Version 4 at the format's largest bits with points far off their prediction: codes of
    up to ``bits + 3`` bits and run differences of ``bits + 4`` keep contexts of their own
    (``PREFIX_LIMIT``; 32 slots raised IndexError writing this)."""
    atlas = random_cube_atlas(3, 2)
    centre = np.array(atlas.vertices).mean(axis=0)
    far = canonical_atlas(AtlasSurface(
        atlas.degree, atlas.spans, atlas.vertices, atlas.quads,
        [tuple(centre + 3 * (np.array(p) - centre)) for p in atlas.edge_points],
        [tuple(centre + 3 * (np.array(p) - centre)) for p in atlas.face_points]))
    back, _ = read_atlas(write_atlas(far, 30, tangent_factor=1.0))
    np.testing.assert_allclose(_points(back), _points(far), rtol=0, atol=1e-6)


def test_placing_with_the_predictions_given_is_placing_without():
    """``FrameCoder.place`` with ``predictions`` made beforehand (the fitter makes them once
    for its three placements of a stage) fills the same points and nearest codes."""
    from client_py.atlas_format import FrameCoder, _Predictor, frame_steps

    atlas = sphere_atlas(3, 2, 3, noise=1e-3)
    axes = [list(a) for a in zip(*_points(atlas), strict=True)]
    n_v = len(atlas.vertices)
    lows, highs = [min(a[:n_v]) for a in axes], [max(a[:n_v]) for a in axes]
    predictor = _Predictor(atlas.quads, atlas.edges, atlas.side, n_v, 10)
    coder = FrameCoder(predictor, atlas.quads, atlas.edges, frame_steps(lows, highs, 10, 2.0))
    frames = coder.frames(list(zip(*[a[:n_v] for a in axes], strict=True)))
    count, n_e = len(axes[0]), coder.n_edge
    for start, stop in ((n_v, n_e), (n_e, count)):
        placed = []
        for made in (False, True):
            out, codes = [list(a) for a in axes], [[0] * count for _ in range(3)]
            predictions = coder.predictions(out, start >= n_e) if made else None
            coder.place(out, frames, start, stop, codes, axes, predictions)
            placed.append((out, codes))
        assert placed[0] == placed[1]
        assert any(c != 0 for c in placed[0][1][1][start:stop])
