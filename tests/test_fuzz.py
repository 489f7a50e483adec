"""client_py's decoders are bounded before they allocate, and keep one error contract.

Issue 15: every hostile input found there as a test (each failed before the fix), then
property-based fuzzing of ``read_patch``, ``read_detail_tile`` and the manifest functions
with a bounded number of examples (the long run is ``python -m bench fuzz``, 10^5 inputs
of each kind). Whatever the bytes or the manifest, only a result or ``PatchFormatError``
comes out, within a time bound.
"""

from __future__ import annotations

import json
import re
import struct
import time
import tracemalloc
import zlib
from functools import cache
from pathlib import Path

import pytest
from fuzz_inputs import (
    check_contract,
    manifest_text,
    mutate_patch,
    mutate_tile,
    random_manifest,
    seed_manifest,
    seed_patch,
    seed_tiles,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from client_py import NurbsSurface
from client_py.atlas import MAX_ATLAS_VERTICES
from client_py.bundle import (
    ManifestError,
    detail_nodes,
    plan_level,
    plan_levels,
    tessellate_bundle,
    texture_nodes,
)
from client_py.control_mesh import ControlMeshCodes, read_control_codes, write_control_codes
from client_py.errors import PatchFormatError
from client_py.format import (
    HEADER,
    LIMITS,
    MAGIC,
    TILE_HEADER,
    read_detail_tile,
    read_patch,
    write_detail_tile,
)
from client_py.layers import DetailTile, level_knots
from client_py.session import WorkerSession

#: wall-clock bounds below: `make test` runs this file alone, after the parallel part
pytestmark = pytest.mark.timing

DOCS = Path(__file__).resolve().parent.parent / "docs" / "format.md"
FUZZ = settings(max_examples=150, deadline=1000, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow])


def _with_crc(body: bytes) -> bytes:
    return body + struct.pack("<I", zlib.crc32(body))


def refused_quickly(call, data, match: str, seconds: float = 1.0, megabytes: float = 300):
    """``call(data)`` raises PatchFormatError matching ``match`` within the time and memory."""
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(PatchFormatError, match=match):
            call(data)
        elapsed = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert elapsed < seconds and peak < megabytes * 1e6, (elapsed, peak)


# --- .tsp: claimed sizes checked before inflating -------------------------------------------
@cache
def claiming_patch(side: int) -> bytes:
    """The issue's amplification file: a valid header and CRC claiming a ``side^2``, 16-bit,
    uniform grid, over a zlib stream of zeros of exactly the payload that grid needs
    (4096: 196 KB inflating to 151 MB)."""
    planes, grids = 3, 3
    raw_size = 8 * (4 + 6) + grids * side * side * planes + 4
    deflate, chunk, parts, left = zlib.compressobj(9), bytes(1 << 20), [], raw_size
    while left:
        parts.append(deflate.compress(chunk[: min(left, len(chunk))]))
        left -= min(left, len(chunk))
    blob = b"".join(parts) + deflate.flush()
    header = HEADER.pack(MAGIC, 1, 4 | 8, 3, 3, side, side, 16, 0, len(blob), raw_size)
    return _with_crc(header + blob)


@pytest.mark.parametrize("side", [4096, 2048])
def test_a_patch_claiming_a_huge_grid_is_refused_within_1s_and_300mb(side):
    data = claiming_patch(side)
    assert len(data) < 200_000
    refused_quickly(read_patch, data, f"n_u = {side} control points > 1024 per side")


def test_a_grid_within_the_side_limit_but_too_many_points_is_refused():
    data = _with_crc(HEADER.pack(MAGIC, 1, 12, 2, 2, 1024, 1024, 16, 0, 10, 10**7)
                     + bytes(10))
    refused_quickly(read_patch, data, "grid 1024x1024 exceeds 262144 control points")


def test_a_payload_claiming_more_than_deflate_can_expand_is_refused_before_inflating():
    blob = zlib.compress(bytes(1000), 9)  # 17 bytes: at most 17 544 could come out
    data = _with_crc(HEADER.pack(MAGIC, 1, 12, 2, 2, 200, 200, 16, 0, len(blob), 400_000)
                     + blob)
    refused_quickly(read_patch, data, f"exceeds the {1032 * len(blob)} bytes a {len(blob)}-byte "
                    "zlib stream can inflate to")


def test_a_payload_below_what_its_grid_needs_is_refused_before_inflating():
    blob = zlib.compress(bytes(100), 9)
    data = _with_crc(HEADER.pack(MAGIC, 1, 12, 2, 2, 200, 200, 16, 0, len(blob), 100) + blob)
    with pytest.raises(PatchFormatError, match="payload size 100 is below the 360086 bytes"):
        read_patch(data)


# --- .tsd: the level bounded, no level-wide knot vector --------------------------------------
def _tile_with(fields: dict, coded: bytes | None = None) -> bytes:
    """A valid tile (level 7, spans 64, zero values) with header ``fields`` replaced."""
    base = write_detail_tile(DetailTile(7, 100, 3, 3, 64, 0.5, (0,) * 67**2))
    names = ["magic", "version", "flags", "level", "degree", "spans", "side", "i", "j", "step"]
    head = dict(zip(names, TILE_HEADER.unpack_from(base), strict=True)) | fields
    body = TILE_HEADER.pack(*head.values())
    return _with_crc(body + (base[TILE_HEADER.size : -4] if coded is None else coded))


def test_a_level_15_tile_is_refused_without_allocating_its_level():
    data = _tile_with({"level": 15, "i": 30000, "j": 20000})
    assert len(data) < 250  # the 222-byte tile: 412 MB of knots before
    refused_quickly(read_detail_tile, data, "level 15 outside 0..7", megabytes=10)


def test_the_deepest_tile_holds_only_its_own_knots():
    data = _tile_with({})
    tracemalloc.start()
    tile = read_detail_tile(data)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 2e6  # values only: the level's 8 199 knots are never built
    full = level_knots(3, 64, 7)
    assert tile.knots == (tuple(full[100 * 64 :][: 64 + 7]), tuple(full[3 * 64 :][: 64 + 7]))


@pytest.mark.parametrize(("fields", "match"), [
    ({"spans": 65}, "spans = 65 outside 1..64"),
    ({"side": 65, "flags": 1}, "drawn mask side 65 outside 1..64"),
])
def test_a_tile_claiming_more_than_the_fitter_writes_is_refused(fields, match):
    refused_quickly(read_detail_tile, _tile_with(fields), match, seconds=0.1, megabytes=1)


def test_a_tile_whose_coded_bytes_end_before_the_decoder_starts_is_a_format_error():
    data = _tile_with({"spans": 2, "degree": 1, "level": 0, "i": 0, "j": 0}, coded=b"\x07")
    with pytest.raises(PatchFormatError, match="coded values end early"):
        read_detail_tile(data)


# --- .tsa control meshes: per-point state for the points the file holds ----------------------
#: the most points two triangles (``E = 5`` edges) leave room for: ``n + E + T`` is the smooth
#: atlas's layout vertices, at most ``MAX_ATLAS_VERTICES`` (client_py.smooth_base)
MOST_POINTS = MAX_ATLAS_VERTICES - 5 - 2


@cache
def two_triangles(version: int, n_points: int) -> bytes:
    """A control mesh of two triangles over points 0..3, its other ``n_points - 4`` points
    in no triangle with codes 0: a valid file, 594 bytes at :data:`MOST_POINTS` in
    version 5 (a residual of 0 costs about a hundredth of a bit once its context has adapted)."""
    codes = [(0, 0, 0), (100, 0, 0), (0, 100, 0), (100, 100, 5)] + [(0, 0, 0)] * (n_points - 4)
    mesh = ControlMeshCodes(codes, [(0, 1, 2), (1, 3, 2)], 12, (0.0,) * 3, (1.0,) * 3, {})
    return write_control_codes(mesh, version)


@pytest.mark.parametrize("version", [5, 6])
def test_a_control_mesh_stating_the_most_points_is_refused_where_its_stream_ends(version):
    body = bytearray(two_triangles(version, 4)[:-4])
    struct.pack_into("<I", body, 12, MOST_POINTS)  # the header's point count
    data = _with_crc(bytes(body))
    assert len(data) < 100
    # before, made up front: version 5 a set, a list and a list of neighbours per stated
    # point (39 MB); version 6 every point's coding step (27 MB, 2.3 s)
    refused_quickly(read_control_codes, data, "coded control mesh ends early", megabytes=10)


def test_a_600_byte_version_5_control_mesh_of_the_most_points_costs_only_its_points():
    data = two_triangles(5, MOST_POINTS)
    assert len(data) < 1000
    tracemalloc.start()
    try:
        mesh = read_control_codes(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert mesh.triangles == [(0, 1, 2), (2, 1, 3)]
    assert mesh.codes[3:] == [(100, 100, 5)] + [(0, 0, 0)] * (MOST_POINTS - 4)
    # the codes' 131,065 tuples and lists of ints: 12.8 MB; 39 MB before (sets per point)
    assert peak < 20e6, peak


# --- manifests: the one error, names confined ------------------------------------------------
@cache
def _zero_tile(level: int, i: int, j: int) -> bytes:
    return write_detail_tile(DetailTile(level, i, j, 2, 16, 0.25, (0,) * 18**2))


def _names_read(manifest):
    """tessellate_bundle over stand-in files, recording the names it asks for."""
    asked = []

    def read(name):
        asked.append(name)
        if name == "base.tsp":
            return seed_patch()
        level, i, j = (int(x) for x in re.findall(r"\d+", name))
        return _zero_tile(level, i, j)

    return asked, read


@pytest.mark.parametrize(("name", "match"), [
    ("../../../../etc/passwd", r"climbs out of the bundle \('\.\.'\)"),
    ("/etc/passwd", "is an absolute path"),
    ("C:/Windows/x.tsd", "is an absolute path"),
    ("detail\\0\\0_0.tsd", "holds a backslash or NUL"),
    ("detail/0/0_0.tsd\0", "holds a backslash or NUL"),
    ("detail/0/0_0.tsd/../../../etc/passwd", "climbs out of the bundle"),
    ("detail/00/0_0.tsd", "is not a bundle file name"),
    ("detail/1/0_0.tsd", "is not node 0/0_0's file"),
    ("texture/0/0_0.webp", "is not node 0/0_0's file"),
    (17, r"must be a file name \(a string\), got 17"),
])
def test_a_tile_file_name_outside_the_bundle_is_refused(name, match):
    manifest = seed_manifest()
    manifest["tiles"]["detail"]["nodes"][0]["file"] = name
    for call in (plan_level, plan_levels, detail_nodes):
        with pytest.raises(ManifestError, match=r"tiles\.detail node \[0\] file .*" + match):
            call(manifest)
    asked, read = _names_read(manifest)
    with pytest.raises(PatchFormatError, match=match):
        tessellate_bundle(manifest, read, resolution=5)
    assert name not in asked


@pytest.mark.parametrize("name", ["/etc/passwd", "../base.tsp", "/dev/zero", "manifest.json"])
def test_a_base_file_other_than_base_tsp_is_refused_before_it_is_read(name):
    manifest = seed_manifest()
    manifest["base"]["file"] = name
    asked, read = _names_read(manifest)
    with pytest.raises(ManifestError, match=r"base\.file '"):
        tessellate_bundle(manifest, read, resolution=5)
    assert asked == []


def test_the_manifest_that_recursed_is_refused_by_its_level():
    manifest = seed_manifest()  # a texture node 5000 levels down: covered() recursed 5000 deep
    manifest["tiles"]["texture"]["nodes"].append(
        {"level": 5000, "i": 0, "j": 0, "file": "texture/5000/0_0.webp"})
    with pytest.raises(ManifestError, match=r"tiles\.texture node \[20\] .* level in 0\.\.7"):
        texture_nodes(manifest)


@pytest.mark.parametrize("kind", ["detail", "texture"])
def test_a_node_listed_twice_is_refused(kind):
    manifest = seed_manifest()  # 20 000 copies of (0, 0, 0) each explored 4^7 descendants
    nodes = manifest["tiles"][kind]["nodes"]
    nodes.append(dict(nodes[1]))
    with pytest.raises(ManifestError, match=rf"tiles\.{kind} node \[{len(nodes) - 1}\] "
                       "repeats node 1/0_0"):
        plan_levels(manifest)


def test_texture_nodes_of_a_deep_sparse_pyramid_stay_fast():
    manifest = seed_manifest()  # every coarse node explores the absent levels below it once
    manifest["tiles"]["texture"]["nodes"] = [
        {"level": k, "i": i, "j": j, "file": f"texture/{k}/{i}_{j}.png"}
        for k in range(6) for i in range(1 << k) for j in range(1 << k)] + [
        {"level": 7, "i": 5, "j": 9, "file": "texture/7/5_9.png"}]
    start = time.perf_counter()
    assert len(texture_nodes(manifest)) == 1 + 4**5
    assert time.perf_counter() - start < 1.0


def test_a_tile_file_holding_another_node_is_a_format_error():
    manifest = seed_manifest()
    _, read = _names_read(manifest)
    with pytest.raises(PatchFormatError, match="detail/1/0_1.tsd holds tile 1/1_0"):
        tessellate_bundle(manifest, lambda name: read(name.replace("0_1", "1_0")),
                          resolution=5)


@pytest.mark.parametrize(("change", "match"), [
    (lambda m: m.update(tiles=[]), r"tiles must be a JSON object, got \[\]"),
    (lambda m: m["tiles"].update(detail="x"), r"tiles\.detail must be a JSON object"),
    (lambda m: m["tiles"]["detail"].update(nodes={"a": 1}), r"tiles\.detail\.nodes must be a list"),
    (lambda m: m["tiles"]["detail"].update(levels=5), r"tiles\.detail\.levels must be a list"),
    (lambda m: m["tiles"]["detail"].update(levels=[{"level": k} for k in range(9)]),
     "at most 8 levels"),
    (lambda m: m["tiles"]["detail"]["levels"].__setitem__(1, "x"),
     r"tiles\.detail\.levels\[1\] must describe level 1, got 'x'"),
    (lambda m: m["tiles"]["detail"]["levels"][1].update(rms="x"),
     r"tiles\.detail\.levels\[1\]\.rms must be a finite number or null, got 'x'"),
    (lambda m: m["tiles"]["detail"].update(spans_per_tile="16"),
     "spans_per_tile must be a positive integer, got '16'"),
    (lambda m: m["tiles"]["detail"].update(spans_per_tile=1000), "at most 64"),
    (lambda m: m["tiles"]["detail"]["nodes"][2].update(bytes="300"),
     r"tiles\.detail node \[2\] bytes must be a byte count >= 0, got '300'"),
    (lambda m: m["tiles"]["detail"]["nodes"].__setitem__(0, None),
     r"tiles\.detail node \[0\] None \(NoneType\) is not a node"),
    (lambda m: m["tiles"]["detail"]["nodes"][1].update(i=2), r"i and j in 0\.\.2\^level - 1"),
    (lambda m: m["tiles"]["texture"].update(nodes=[[]]), r"tiles\.texture node \[0\] \[\]"),
])
def test_a_malformed_manifest_is_a_manifest_error(change, match):
    manifest = seed_manifest()
    change(manifest)
    with pytest.raises(ManifestError, match=match):
        plan_levels(manifest)
        texture_nodes(manifest)
    session = WorkerSession()
    with pytest.raises(ManifestError, match=match):
        session.read_manifest(json.dumps(manifest))


@pytest.mark.parametrize(("text", "match"), [
    ("[" * 100_000 + "]" * 100_000, "manifest.json is not valid JSON: nested too deep"),
    ("{not json", "manifest.json is not valid JSON"),
    ("[1, 2]", "manifest.json must be a JSON object, got list"),
])
def test_the_session_refuses_a_manifest_it_cannot_read(text, match):
    with pytest.raises(ManifestError, match=match):
        WorkerSession().read_manifest(text)


def test_manifest_errors_pickle_and_are_format_errors():
    import pickle

    err = pickle.loads(pickle.dumps(ManifestError("base.file", "is bad")))
    assert isinstance(err, PatchFormatError) and err.where == "base.file"
    assert str(err) == "invalid bundle manifest: base.file is bad"


def test_tessera_tessellate_on_a_bundle_naming_a_file_outside_it_prints_one_line(tmp_path,
                                                                                  capsys):
    from fitter.cli import main

    bundle = tmp_path / "hostile"
    bundle.mkdir()
    (bundle / "base.tsp").write_bytes(seed_patch())
    manifest = seed_manifest()
    manifest["tiles"]["detail"]["nodes"][0]["file"] = "../../../../etc/passwd"
    (bundle / "manifest.json").write_text(json.dumps(manifest))
    assert main(["tessellate", str(bundle), "--level", "0", "-o", str(tmp_path / "x.ply")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "climbs out of the bundle" in err
    assert "Traceback" not in err


# --- the limits: one table, the same in docs/format.md ---------------------------------------
def test_the_documented_limits_are_the_code_s():
    text = DOCS.read_text()
    section = text[text.index("## Limits") : text.index("## Size")]
    rows = dict(re.findall(r"^\| ([a-z ]+) \| (\d+) \|", section, re.MULTILINE))
    assert {name: int(value) for name, value in rows.items()} == LIMITS


# --- fuzzing: only a result or PatchFormatError, each input quickly ---------------------------
@FUZZ
@given(st.randoms(use_true_random=False))
def test_fuzzed_patches_decode_or_raise_the_format_error(rnd):
    data = mutate_patch(rnd, seed_patch())
    assert check_contract(read_patch, data) is None


@FUZZ
@given(st.randoms(use_true_random=False), st.integers(0, 1))
def test_fuzzed_tiles_decode_or_raise_the_format_error(rnd, which):
    data = mutate_tile(rnd, seed_tiles()[which])
    assert check_contract(read_detail_tile, data) is None


def _every_manifest_call(manifest) -> None:
    asked, read = _names_read(manifest)
    for call in (plan_levels, detail_nodes, texture_nodes, plan_level):
        check = check_contract(call, manifest)
        assert check is None, f"{call.__name__}: {check}"
    check = check_contract(tessellate_bundle, manifest, read, None, 5)
    assert check is None, f"tessellate_bundle: {check}"
    assert all(name == "base.tsp" or name.startswith("detail/") for name in asked)
    session = WorkerSession()
    session.load_patch(seed_patch(), "fuzz")
    check = check_contract(session.read_manifest, manifest_text(manifest))
    assert check is None, f"read_manifest: {check}"


@FUZZ
@given(st.randoms(use_true_random=False))
def test_fuzzed_manifests_plan_or_raise_the_format_error(rnd):
    _every_manifest_call(random_manifest(rnd))


def test_the_fuzz_seeds_are_valid():
    assert isinstance(read_patch(seed_patch()), NurbsSurface)
    assert [read_detail_tile(t).level for t in seed_tiles()] == [0, 2]
    assert len(plan_levels(seed_manifest())) == 2
