"""Hostile scan files: every reader answers a bad file with a ScanError that names it and
says what is wrong, before allocating from what the file claims (issue 15, readers).

The property-based fuzzers run ``FUZZ_EXAMPLES`` examples each (a bounded number in
``make test``); ``TESSERA_FUZZ_EXAMPLES=100000`` runs the long version. Files are
written here with struct/json/plain text, independently of the readers.
"""

from __future__ import annotations

import base64
import gzip
import json
import os
import resource
import struct
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fitter.fitting.io import Scan, ScanError, load_scan

#: wall-clock bounds below: `make test` runs this file alone, after the parallel part
pytestmark = pytest.mark.timing

FUZZ_EXAMPLES = int(os.environ.get("TESSERA_FUZZ_EXAMPLES", "150"))
FUZZ = settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

XYZ_HEADER = "property float x\nproperty float y\nproperty float z\n"


def ply_header(fmt: str, elements: str) -> bytes:
    return f"ply\nformat {fmt} 1.0\n{elements}end_header\n".encode()


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _status_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def reset_peak_rss() -> int | None:
    """Reset this process's peak RSS (Linux: ``5`` into ``/proc/self/clear_refs``) and return
    the resident KiB now, or None where that cannot be done. The pytest process has run other
    tests first, so its lifetime peak (``ru_maxrss``) says nothing about one load."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return _status_kib("VmRSS")
    except (OSError, KeyError):
        return None


def peak_rss_growth_mib(since_kib: int) -> float:
    """MiB the peak RSS rose above ``since_kib`` (from :func:`reset_peak_rss`)."""
    return (_status_kib("VmHWM") - since_kib) / 1024


# ------------------------------------------------------------ PLY: claimed counts


@pytest.mark.parametrize("count", [10**12, 10**6])
def test_an_ascii_ply_claiming_more_vertices_than_its_size_is_refused_before_allocating(
        tmp_path, count):
    path = tmp_path / "huge.ply"
    path.write_bytes(ply_header("ascii", f"element vertex {count}\n{XYZ_HEADER}") + b"0 0 0\n")
    before, start = peak_rss_mib(), time.perf_counter()
    with pytest.raises(ScanError, match=rf"huge\.ply: truncated ASCII PLY: the header promises "
                                        rf"{count} vertices but the file holds only 1 at most"):
        load_scan(path)
    assert time.perf_counter() - start < 0.5 and peak_rss_mib() - before < 50


def test_a_binary_ply_claiming_more_vertices_than_its_size_is_refused(tmp_path):
    path = tmp_path / "huge.ply"
    body = struct.pack("<3f", 1, 2, 3) * 2
    path.write_bytes(ply_header("binary_little_endian",
                                f"element vertex {10**12}\n{XYZ_HEADER}") + body)
    with pytest.raises(ScanError, match=r"huge\.ply: truncated binary PLY: the header promises "
                                        r"1000000000000 vertices but the file holds only 2 "
                                        r"at most: 24 bytes .* 12 bytes \(2 whole vertices\)"):
        load_scan(path)


def test_a_face_count_beyond_the_file_is_refused_before_trimesh_sees_it(tmp_path):
    path = tmp_path / "mesh.ply"
    elements = (f"element vertex 3\n{XYZ_HEADER}element face {10**11}\n"
                "property list uchar int vertex_indices\n")
    path.write_bytes(ply_header("binary_big_endian", elements)
                     + struct.pack(">9f", 0, 0, 0, 1, 0, 0, 0, 1, 0) + b"\x03" + bytes(12))
    with pytest.raises(ScanError, match=r"promises 100000000000 faces but the file holds only "
                                        r"13 at most: 13 bytes are left for them"):
        load_scan(path)
    path.write_bytes(ply_header("ascii", elements) + b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(ScanError, match=r"truncated ASCII PLY: the header promises "
                                        r"100000000000 faces"):
        load_scan(path)


def test_a_gzipped_ply_is_bounded_by_the_deflate_ratio(tmp_path):
    path = tmp_path / "huge.ply.gz"
    data = ply_header("ascii", f"element vertex {10**12}\n{XYZ_HEADER}") + b"0 0 0\n"
    path.write_bytes(gzip.compress(data))
    with pytest.raises(ScanError, match=r"huge\.ply\.gz: truncated ASCII PLY: .* gzip file "
                                        r"decompresses to at most 1032 times its size"):
        load_scan(path)


def test_a_gzipped_ascii_ply_within_the_bound_is_read_line_by_line_to_its_end(tmp_path):
    # the deflate bound admits the claim; the streamed reader then finds the lines missing
    path = tmp_path / "short.ply.gz"
    rows = np.random.default_rng(3).uniform(-1, 1, (200, 3))
    body = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in rows).encode()
    path.write_bytes(gzip.compress(ply_header("ascii", f"element vertex 1000\n{XYZ_HEADER}")
                                   + body))
    with pytest.raises(ScanError, match=r"short\.ply\.gz: truncated ASCII PLY: the header "
                                        r"promises 1000 vertices but the file holds only 200 "
                                        r"vertex lines"):
        load_scan(path)


# ------------------------------------------------------------ PLY: fuzzing

SCALAR_TYPES = ["char", "uchar", "short", "ushort", "int", "uint", "float", "double"]
PROPERTY_NAMES = ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "confidence"]


@st.composite
def ply_files(draw) -> bytes:
    """Headers with random formats, elements, property types and counts, and bodies that
    are random bytes, random numbers, or a prefix of them."""
    fmt = draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]))
    lines = []
    for element in draw(st.lists(st.sampled_from(["vertex", "face", "range_grid", "other"]),
                                 min_size=1, max_size=3)):
        count = draw(st.one_of(st.integers(0, 8), st.integers(0, 10**15)))
        lines.append(f"element {element} {count}")
        names = draw(st.lists(st.sampled_from(PROPERTY_NAMES), max_size=6, unique=True))
        if draw(st.booleans()):
            names = ["x", "y", "z", *[n for n in names if n not in "xyz"]]
        for name in names:
            lines.append(f"property {draw(st.sampled_from(SCALAR_TYPES))} {name}")
        if element == "face" or draw(st.integers(0, 4)) == 0:
            count_type = draw(st.sampled_from(["uchar", "int", "float", "uint"]))
            lines.append(f"property list {count_type} {draw(st.sampled_from(SCALAR_TYPES))} "
                         "vertex_indices")
    header = ply_header(fmt, "".join(line + "\n" for line in lines))
    if fmt == "ascii":
        numbers = draw(st.lists(st.one_of(st.integers(-300, 300), st.floats(width=32)),
                                max_size=60))
        body = " ".join(map(str, numbers)).replace(" ", draw(st.sampled_from([" ", "\n"])),
                                                   draw(st.integers(0, 60))).encode()
    else:
        body = draw(st.binary(max_size=400))
    data = header + body
    if draw(st.booleans()):  # a corrupted copy: a byte flipped or the file cut short
        position = draw(st.integers(0, len(data) - 1))
        if draw(st.booleans()):
            data = data[:position] + bytes([data[position] ^ draw(st.integers(1, 255))]) \
                + data[position + 1:]
        else:
            data = data[:position]
    return data


@st.composite
def mutated_valid_ply_files(draw) -> bytes:
    """A valid small cloud or triangle mesh (ASCII or binary), then one element count
    replaced (up to 10^15), a byte flipped, or the file cut short."""
    fmt = draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]))
    n = draw(st.integers(1, 6))
    points = draw(st.lists(st.floats(-1e3, 1e3, width=32), min_size=3 * n, max_size=3 * n))
    faces = [(0, i % n, (i + 1) % n) for i in range(draw(st.integers(0, 3)))]
    elements = f"element vertex {n}\n{XYZ_HEADER}"
    if faces:
        elements += f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
    if fmt == "ascii":
        body = "".join(f"{points[3 * i]} {points[3 * i + 1]} {points[3 * i + 2]}\n"
                       for i in range(n))
        body += "".join(f"3 {a} {b} {c}\n" for a, b, c in faces)
        data = ply_header(fmt, elements) + body.encode()
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        data = ply_header(fmt, elements) + struct.pack(f"{order}{3 * n}f", *points)
        data += b"".join(struct.pack(f"{order}B3i", 3, *f) for f in faces)
    mutation = draw(st.sampled_from(["count", "flip", "cut"]))
    if mutation == "count":
        old = draw(st.sampled_from([f"vertex {n}", f"face {len(faces)}"]))
        new = old.split()[0] + f" {draw(st.integers(0, 10**15))}"
        data = data.replace(old.encode(), new.encode(), 1)
    else:
        position = draw(st.integers(0, len(data) - 1))
        data = (data[:position] + bytes([data[position] ^ draw(st.integers(1, 255))])
                + data[position + 1:]) if mutation == "flip" else data[:position]
    return data


def load_or_scan_error(data: bytes, suffix: str, gzipped: bool = False) -> Scan | None:
    """Write ``data`` to a scratch file, load it: a Scan or None for a ScanError; anything
    else (and any slow or memory-hungry load) fails the test."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"fuzz{suffix}{'.gz' if gzipped else ''}"
        path.write_bytes(gzip.compress(data, mtime=0) if gzipped else data)
        start = time.perf_counter()
        try:
            scan = load_scan(path)
        except ScanError as exc:
            assert path.name in str(exc), str(exc)  # the message names the file
            scan = None
        assert time.perf_counter() - start < 5, "a small hostile file took over 5 s"
    return scan


@FUZZ
@given(data=st.one_of(ply_files(), mutated_valid_ply_files()), gzipped=st.booleans())
def test_fuzzed_ply_files_raise_only_scan_error(data, gzipped):
    baseline = reset_peak_rss()
    scan = load_or_scan_error(data, ".ply", gzipped)
    assert scan is None or np.isfinite(scan.points).all()
    if baseline is not None:
        assert peak_rss_growth_mib(baseline) < 1024, "a fuzzed PLY took more than 1 GiB"


# ------------------------------------------------------------ text encodings of OBJ/OFF

OBJ_LATIN1 = "# mod\xe8le de la fa\xe7ade\no fa\xe7ade\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
OFF_CP1252 = "OFF\n# \u201cbust\u201d \u2013 \u20ac 12\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"


@pytest.mark.parametrize("name,text,encoding", [
    ("latin1.obj", OBJ_LATIN1, "latin-1"), ("cp1252.obj", OBJ_LATIN1.replace("\xe8", "\u0153"),
                                            "cp1252"),
    ("latin1.off", OFF_CP1252.replace("\u201c", "\xab").replace("\u201d", "\xbb")
     .replace("\u2013", "-").replace("\u20ac", "\xa3"), "latin-1"),
    ("cp1252.off", OFF_CP1252, "cp1252")])
def test_non_utf8_obj_and_off_are_read_as_latin1(tmp_path, name, text, encoding):
    data = text.encode(encoding)
    with pytest.raises(UnicodeDecodeError):
        data.decode("utf-8")  # the case trimesh sent to charset_normalizer
    (tmp_path / name).write_bytes(data)
    scan = load_scan(tmp_path / name)
    np.testing.assert_array_equal(scan.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(scan.faces, [[0, 1, 2]])
    assert f"{name} is not UTF-8: read as Latin-1" in scan.source["warnings"]


def test_a_latin1_mtl_beside_an_obj_is_read(tmp_path):
    (tmp_path / "m.mtl").write_bytes("# mat\xe9riau\nnewmtl pierre\nKd 0.8 0.7 0.6\n"
                                     .encode("latin-1"))
    (tmp_path / "m.obj").write_text("mtllib m.mtl\nusemtl pierre\nv 0 0 0\nv 1 0 0\nv 0 1 0\n"
                                    "f 1 2 3\n")
    scan = load_scan(tmp_path / "m.obj")
    assert len(scan.points) == 3
    assert "companion file 'm.mtl' is not UTF-8: read as Latin-1" in scan.source["warnings"]
    assert [f["name"] for f in scan.source["files"]] == ["m.obj", "m.mtl"]


def test_a_latin1_ascii_stl_is_read(tmp_path):
    text = ("solid pi\xe8ce\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n"
            "vertex 0 1 0\nendloop\nendfacet\nendsolid pi\xe8ce\n")
    (tmp_path / "p.stl").write_bytes(text.encode("latin-1"))
    assert len(load_scan(tmp_path / "p.stl").points) == 3


# ------------------------------------------------------------ glTF / GLB

def gltf_tree(buffer: bytes, view_length: int | None = None, count: int = 3,
              declared: int | None = None) -> dict:
    uri = "data:application/octet-stream;base64," + base64.b64encode(buffer).decode()
    return {"asset": {"version": "2.0"},
            "buffers": [{"byteLength": len(buffer) if declared is None else declared,
                         "uri": uri}],
            "bufferViews": [{"buffer": 0, "byteOffset": 0,
                             "byteLength": len(buffer) if view_length is None else view_length}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": count,
                           "type": "VEC3"}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}], "scene": 0}


TRIANGLE = struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)


def glb(tree: dict, binary: bytes = b"") -> bytes:
    text = json.dumps(tree).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text
    if binary:
        chunks += struct.pack("<I4s", len(binary), b"BIN\x00") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def test_a_valid_gltf_and_glb_still_load(tmp_path):
    (tmp_path / "ok.gltf").write_text(json.dumps(gltf_tree(TRIANGLE)))
    assert len(load_scan(tmp_path / "ok.gltf").points) == 3
    tree = gltf_tree(TRIANGLE)
    del tree["buffers"][0]["uri"]
    (tmp_path / "ok.glb").write_bytes(glb(tree, TRIANGLE))
    assert len(load_scan(tmp_path / "ok.glb").points) == 3


@pytest.mark.parametrize("content,message", [
    (b"this is not json \x00", r"not JSON \(Expecting value at line 1, column 1\)"),
    (b"\xff\xfe{}", r"its JSON is not UTF-8 text"),
    (b"[1, 2]", r"the JSON is a list, not an object"),
    (b'{"meshes": []}', r"not glTF 2\.0: no 'asset'"),
    (b'{"asset": {"version": "1.0"}}', r"not glTF 2\.0: asset\.version is '1\.0'"),
    (json.dumps({**gltf_tree(TRIANGLE), "buffers": []}).encode(),
     r"it has bufferViews or accessors but no "
     r"'buffers'"),
    (json.dumps({**gltf_tree(TRIANGLE), "buffers": {"a": 1}}).encode(),
     r"glTF 'buffers' must be a list of objects"),
])
def test_a_garbage_gltf_says_what_is_wrong(tmp_path, content, message):
    (tmp_path / "garbage.gltf").write_bytes(content)
    with pytest.raises(ScanError, match=r"garbage\.gltf: unreadable GLTF content: " + message):
        load_scan(tmp_path / "garbage.gltf")


def test_a_buffer_view_overrunning_its_buffer_is_a_scan_error(tmp_path):
    (tmp_path / "overrun.gltf").write_text(json.dumps(gltf_tree(TRIANGLE, view_length=3600)))
    with pytest.raises(ScanError, match=r"overrun\.gltf: unreadable GLTF content: bufferViews\[0\] "
                                        r"\(bytes 0\.\.3600\) "
                                        r"overruns buffers\[0\], which has 36 bytes"):
        load_scan(tmp_path / "overrun.gltf")


def test_a_buffer_shorter_than_its_declared_length_is_a_scan_error(tmp_path):
    # the declared lengths agree, the data does not: trimesh's assert, reported by us
    tree = gltf_tree(TRIANGLE[:24], view_length=36, declared=36)
    (tmp_path / "short.gltf").write_text(json.dumps(tree))
    with pytest.raises(ScanError, match=r"short\.gltf: inconsistent GLTF layout: a bufferView "
                                        r"or accessor reaches past the data its buffer"):
        load_scan(tmp_path / "short.gltf")


def test_an_accessor_overrunning_its_view_is_a_scan_error(tmp_path):
    (tmp_path / "acc.gltf").write_text(json.dumps(gltf_tree(TRIANGLE, count=1000)))
    with pytest.raises(ScanError, match=r"acc\.gltf: unreadable GLTF content: accessors\[0\] "
                                        r"\(1000 x VEC3 of 12 bytes "
                                        r".* overruns bufferViews\[0\], which has 36 bytes"):
        load_scan(tmp_path / "acc.gltf")


@pytest.mark.parametrize("mutate,message", [
    (lambda b: b"glTX" + b[4:], r"not a GLB file: it starts with b'glTX'"),
    (lambda b: b[:4] + struct.pack("<I", 1) + b[8:], r"not glTF 2\.0: the GLB header states "
                                                     r"version 1"),
    (lambda b: b[:-10], r"truncated GLB: the header states \d+ bytes"),
    (lambda b: b[:16] + b"BIN\x00" + b[20:],
     r"not a GLB file: its first chunk is b'BIN\\x00', not b'JSON'"),
    (lambda b: b[:10], r"not a GLB file: 10 bytes"),
])
def test_a_broken_glb_says_what_is_wrong(tmp_path, mutate, message):
    tree = gltf_tree(TRIANGLE)
    del tree["buffers"][0]["uri"]
    (tmp_path / "b.glb").write_bytes(mutate(glb(tree, TRIANGLE)))
    with pytest.raises(ScanError, match=r"b\.glb: unreadable GLB content: " + message):
        load_scan(tmp_path / "b.glb")


def test_a_missing_or_escaping_gltf_buffer_file_is_a_scan_error(tmp_path):
    tree = gltf_tree(TRIANGLE)
    tree["buffers"][0]["uri"] = "missing.bin"
    (tmp_path / "m.gltf").write_text(json.dumps(tree))
    with pytest.raises(ScanError, match=r"m\.gltf: cannot read its companion file "
                                        r"'missing\.bin'"):
        load_scan(tmp_path / "m.gltf")
    (tmp_path / "outside.bin").write_bytes(TRIANGLE)
    (tmp_path / "inner").mkdir()
    tree["buffers"][0]["uri"] = "../outside.bin"
    (tmp_path / "inner" / "e.gltf").write_text(json.dumps(tree))
    with pytest.raises(ScanError, match=r"e\.gltf: cannot read its companion file "
                                        r"'\.\./outside\.bin'.*outside the scan's folder"):
        load_scan(tmp_path / "inner" / "e.gltf")


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 10**12) | st.floats() | st.text(max_size=8),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.sampled_from(["buffer", "byteLength", "byteOffset", "byteStride",
                                       "count", "type", "componentType", "bufferView", "uri",
                                       "version", "POSITION", "attributes", "indices"]),
                      children, max_size=4), max_leaves=12)


@st.composite
def gltf_trees(draw) -> dict:
    """A valid triangle's tree with some entries replaced by arbitrary JSON values."""
    tree = gltf_tree(TRIANGLE)
    for _ in range(draw(st.integers(1, 4))):
        table = draw(st.sampled_from(["buffers", "bufferViews", "accessors", "meshes", "asset"]))
        entry = tree[table] if table == "asset" else tree[table][0]
        key = draw(st.sampled_from(sorted(entry) + ["byteStride", "byteOffset", "sparse"]))
        entry[key] = draw(JSON_VALUES)
    return tree


@FUZZ
@given(tree=gltf_trees(), as_glb=st.booleans())
def test_fuzzed_gltf_and_glb_raise_only_scan_error(tree, as_glb):
    data = glb(tree) if as_glb else json.dumps(tree).encode()
    load_or_scan_error(data, ".glb" if as_glb else ".gltf")


@FUZZ
@given(text=st.sampled_from([OBJ_LATIN1, OFF_CP1252.replace("\u20ac", "E")]),
       edits=st.lists(st.tuples(st.integers(0, 200), st.binary(min_size=0, max_size=4)),
                      min_size=1, max_size=4))
def test_fuzzed_obj_and_off_raise_only_scan_error(text, edits):
    data = bytearray(text.encode("latin-1", errors="replace"))
    for position, replacement in edits:
        position = min(position, len(data))
        data[position:position + len(replacement)] = replacement
    load_or_scan_error(bytes(data), ".off" if text.startswith("OFF") else ".obj")
