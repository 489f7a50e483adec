"""Scanner formats: ASTM E57 (pye57) and LAS/LAZ (laspy + lazrs), read and fitted.

Every file here is written by the same library that the reader uses (pye57, laspy), so the
tests check our reading against an independent writer: poses applied as numpy applies
them, colours and scaled coordinates as the writer stored them, LAZ equal to LAS, and the
same cloud as PLY and as E57 giving the same ``base.tsp`` bytes.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import struct
import uuid

import laspy
import numpy as np
import pye57
import pytest
from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct, WktCoordinateSystemVlr
from pye57 import libe57
from scipy.spatial.transform import Rotation

from client_py.ply import write_points_ply
from fitter.cli import main as tessera
from fitter.collection.uploads import (
    ReceivedFile,
    UploadError,
    UploadLimits,
    prepare_scan,
    sniff_format,
)
from fitter.fitting.examples import relief_scan
from fitter.fitting.io import InputLimits, ScanError, load_scan
from fitter.fitting.io.las import parse_wkt, units_of_geo_keys, units_of_wkt
from fitter.fitting.options import FitOptions
from fitter.fitting.pipeline import fit_scan

RNG = np.random.default_rng(16)


# ----------------------------------------------------------------------------- writers
def write_e57(path, scans):
    """An E57 of ``scans``: dicts with ``xyz (n, 3)``, optional ``rgb (n, 3)`` uint8,
    ``intensity (n,)``, ``invalid (n,)`` int8, ``rotation`` (w, x, y, z),
    ``translation`` and ``name``, through pye57's ``write_scan_raw``."""
    with pye57.E57(str(path), mode="w") as e57:
        for scan in scans:
            xyz = np.asarray(scan["xyz"], np.float64)
            data = {"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2]}
            if "rgb" in scan:
                for i, key in enumerate(("colorRed", "colorGreen", "colorBlue")):
                    data[key] = np.ascontiguousarray(scan["rgb"][:, i])
            if "intensity" in scan:
                data["intensity"] = scan["intensity"]
            if "invalid" in scan:
                data["cartesianInvalidState"] = scan["invalid"].astype(np.int8)
            e57.write_scan_raw(data, name=scan.get("name", "scan"),
                               rotation=np.asarray(scan.get("rotation", [1.0, 0, 0, 0])),
                               translation=np.asarray(scan.get("translation", [0.0, 0, 0])))


def write_spherical_e57(path, rae, invalid, rotation, translation):
    """An E57 with one spherical scan (range, azimuth, elevation in double precision and a
    ``sphericalInvalidState``), built node by node with libE57Format (pye57 writes only
    cartesian scans)."""
    with pye57.E57(str(path), mode="w") as e57:
        imf = e57.image_file
        scan = libe57.StructureNode(imf)
        scan.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
        scan.set("name", libe57.StringNode(imf, "spherical"))
        pose = libe57.StructureNode(imf)
        rot = libe57.StructureNode(imf)
        # children in x y z w order, unlike pye57's w x y z: the reader must go by name
        for key in "xyzw":
            rot.set(key, libe57.FloatNode(imf, float(rotation["wxyz".index(key)])))
        move = libe57.StructureNode(imf)
        for key, value in zip("xyz", translation, strict=True):
            move.set(key, libe57.FloatNode(imf, float(value)))
        pose.set("rotation", rot)
        pose.set("translation", move)
        scan.set("pose", pose)
        prototype = libe57.StructureNode(imf)
        fields = ["sphericalRange", "sphericalAzimuth", "sphericalElevation"]
        for i, field in enumerate(fields):
            low, high = float(rae[:, i].min()), float(rae[:, i].max())
            prototype.set(field, libe57.FloatNode(imf, low, libe57.E57_DOUBLE, low, high))
        prototype.set("sphericalInvalidState", libe57.IntegerNode(imf, 0, 0, 2))
        points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
        scan.set("points", points)
        e57.data3d.append(scan)
        arrays, buffers = e57.make_buffers(fields + ["sphericalInvalidState"], len(rae))
        for i, field in enumerate(fields):
            arrays[field][:] = rae[:, i]
        arrays["sphericalInvalidState"][:] = invalid
        writer = points.writer(buffers)
        writer.write(len(rae))
        writer.close()


def write_las(path, xyz, rgb=None, intensity=None, scales=(0.001, 0.001, 0.001),
              offsets=(1000.0, 2000.0, 10.0), vlrs=(), version="1.2"):
    """A LAS (or, by the ``.laz`` name, LAZ) file through laspy; the LasData written."""
    header = laspy.LasHeader(point_format=3 if rgb is not None else 1, version=version)
    header.scales, header.offsets = np.array(scales), np.array(offsets)
    for vlr in vlrs:
        header.vlrs.append(vlr)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if rgb is not None:
        las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    if intensity is not None:
        las.intensity = intensity
    las.write(str(path))
    return las


def random_cloud(n, scale=1.0):
    return RNG.uniform(-1.0, 1.0, (n, 3)) * scale


# --------------------------------------------------------------------------------- E57
def test_e57_two_scans_poses_applied_colour_kept(tmp_path):
    a_xyz, b_xyz = random_cloud(700, 2.0), random_cloud(500, 3.0)
    a_rgb = RNG.integers(0, 256, (700, 3), dtype=np.uint8)
    b_rgb = RNG.integers(0, 256, (500, 3), dtype=np.uint8)
    qa = Rotation.from_euler("xyz", [10, -40, 75], degrees=True).as_quat()  # x y z w
    qb = Rotation.from_euler("zyx", [-120, 5, 30], degrees=True).as_quat()
    ta, tb = np.array([1.5, -2.0, 0.25]), np.array([-10.0, 4.0, 3.0])
    path = tmp_path / "site.e57"
    write_e57(path, [
        {"xyz": a_xyz, "rgb": a_rgb, "intensity": RNG.random(700), "name": "north",
         "rotation": [qa[3], *qa[:3]], "translation": ta},
        {"xyz": b_xyz, "rgb": b_rgb, "intensity": RNG.random(500), "name": "south",
         "rotation": [qb[3], *qb[:3]], "translation": tb},
    ])
    scan = load_scan(path)
    # pye57 stores the coordinates in single precision; the pose is applied on our side
    stored_a, stored_b = a_xyz.astype(np.float32), b_xyz.astype(np.float32)
    expected = np.vstack([Rotation.from_quat(qa).apply(stored_a) + ta,
                          Rotation.from_quat(qb).apply(stored_b) + tb])
    np.testing.assert_allclose(scan.points, expected, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(scan.colors, np.vstack([a_rgb, b_rgb]))
    assert scan.units == "m" and scan.source["format"] == "e57"
    assert scan.source["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    names = [(s["name"], s["points"], s["points_claimed"]) for s in scan.source["scans"]]
    assert names == [("north", 700, 700), ("south", 500, 500)]
    assert scan.source["scans"][0]["pose"]["translation"] == ta.tolist()
    lo, hi = scan.source["scans"][0]["intensity"]
    assert 0 <= lo < hi <= 1
    assert any("intensity" in w for w in scan.source["warnings"])


def test_e57_invalid_points_dropped_and_colour_of_some_scans_not_kept(tmp_path):
    xyz = random_cloud(400)
    invalid = np.zeros(400, np.int8)
    invalid[::4], invalid[1::9] = 2, 1
    path = tmp_path / "holes.e57"
    write_e57(path, [{"xyz": xyz, "invalid": invalid, "rgb": np.full((400, 3), 9, np.uint8)},
                     {"xyz": random_cloud(50)}])
    scan = load_scan(path)
    keep = invalid == 0
    np.testing.assert_array_equal(scan.points[:keep.sum()], xyz[keep].astype(np.float32))
    assert scan.n_points == keep.sum() + 50
    assert scan.source["scans"][0]["invalid_dropped"] == int((~keep).sum())
    assert scan.colors is None
    assert any("colour not kept" in w for w in scan.source["warnings"])


def test_e57_spherical_scan_converted_posed_and_invalid_dropped(tmp_path):
    n = 300
    rae = np.column_stack([RNG.uniform(1, 20, n), RNG.uniform(-np.pi, np.pi, n),
                           RNG.uniform(-1.2, 1.2, n)])
    invalid = (RNG.random(n) < 0.2).astype(np.int8) * 2
    q = Rotation.from_euler("xyz", [0, 0, 33], degrees=True).as_quat()
    t = np.array([5.0, 6.0, 7.0])
    path = tmp_path / "sphere.e57"
    write_spherical_e57(path, rae, invalid, [q[3], *q[:3]], t)
    scan = load_scan(path)
    r, az, el = rae[invalid == 0].T  # the E57 standard's spherical coordinates
    local = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                             r * np.sin(el)])
    np.testing.assert_allclose(scan.points, Rotation.from_quat(q).apply(local) + t,
                               rtol=0, atol=1e-9)
    assert scan.source["scans"][0]["coordinates"] == "spherical"


def test_e57_fit_end_to_end_records_provenance(tmp_path):
    points = relief_scan(4_000, seed=5) / 1000.0  # mm -> m, as E57 holds
    path = tmp_path / "relief.e57"
    write_e57(path, [{"xyz": points, "name": "relief"}])
    bundle = fit_scan(path, tmp_path / "bundle", FitOptions(grid=(8, 8)))
    manifest = json.loads((bundle.path / "manifest.json").read_text())
    provenance = manifest["provenance"]
    assert provenance["format"] == "e57" and provenance["points"] == 4_000
    assert provenance["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert provenance["bytes"] == path.stat().st_size
    assert manifest["units"] == "m"


def test_same_cloud_as_ply_and_e57_gives_the_same_base_patch(tmp_path):
    points = relief_scan(5_000, seed=7).astype(np.float32)  # E57 single precision = PLY's
    colours = RNG.integers(0, 256, (5_000, 3), dtype=np.uint8)
    ply, e57 = tmp_path / "relief.ply", tmp_path / "relief.e57"
    # the patch's metadata holds the units: the PLY states the metres E57 has by definition
    ply.write_bytes(write_points_ply(points, colours, comments=["units m"]))
    write_e57(e57, [{"xyz": points.astype(np.float64), "rgb": colours}])
    np.testing.assert_array_equal(load_scan(ply).points, load_scan(e57).points)
    options = FitOptions(grid=(10, 10))
    a = fit_scan(ply, tmp_path / "from_ply", options)
    b = fit_scan(e57, tmp_path / "from_e57", options)
    assert (a.path / "base.tsp").read_bytes() == (b.path / "base.tsp").read_bytes()


def test_e57_bad_files(tmp_path):
    good = tmp_path / "good.e57"
    write_e57(good, [{"xyz": random_cloud(2_000)}])
    data = good.read_bytes()

    truncated = tmp_path / "truncated.e57"
    truncated.write_bytes(data[:len(data) // 2])
    with pytest.raises(ScanError, match=r"truncated\.e57: truncated E57 file: the header "
                                        r"states [\d,]+ bytes"):
        load_scan(truncated)

    text = tmp_path / "text.e57"
    text.write_text("1 2 3\n4 5 6\n")
    with pytest.raises(ScanError, match=r"text\.e57: not an E57 file: it starts with"):
        load_scan(text)

    empty = tmp_path / "empty.e57"
    pye57.E57(str(empty), mode="w").close()
    with pytest.raises(ScanError, match=r"empty\.e57: the file contains no points"):
        load_scan(empty)

    all_invalid = tmp_path / "invalid.e57"
    write_spherical_e57(all_invalid, RNG.uniform(1, 2, (30, 3)), np.full(30, 2, np.int8),
                        [1.0, 0, 0, 0], [0.0, 0, 0])
    with pytest.raises(ScanError, match=r"invalid\.e57: the file contains no points: all 30 "
                                        "points .* marked invalid"):
        load_scan(all_invalid)

    no_rotation = tmp_path / "pose.e57"
    write_spherical_e57(no_rotation, RNG.uniform(1, 2, (30, 3)), np.zeros(30, np.int8),
                        [0.0, 0, 0, 0], [0.0, 0, 0])
    with pytest.raises(ScanError, match=r"pose\.e57: scan 0 \('spherical'\) has a pose with "
                                        "a zero or non-finite rotation"):
        load_scan(no_rotation)

    corrupt = tmp_path / "corrupt.e57"  # right signature and length, the pages garbled
    body = bytearray(data)
    body[2048:2048 + 512] = bytes(512)
    corrupt.write_bytes(bytes(body))
    with pytest.raises(ScanError, match=r"corrupt\.e57: corrupt E57 file"):
        load_scan(corrupt)

    with pytest.raises(ScanError, match=r"good\.e57: 2,000 points, over the limit "
                                        "max_points = 1,000"):
        load_scan(good, limits=InputLimits(max_points=1_000))

    zipped = tmp_path / "good.e57.gz"
    zipped.write_bytes(gzip.compress(data))
    with pytest.raises(ScanError, match=r"good\.e57\.gz: a gzip-compressed E57 file is not "
                                        "read"):
        load_scan(zipped)


# ----------------------------------------------------------------------------- LAS/LAZ
def test_las_scaled_coordinates_rgb_and_laz_equal_to_las(tmp_path):
    n = 3_000
    xyz = np.column_stack([1000 + RNG.random(n) * 50, 2000 + RNG.random(n) * 40,
                           10 + RNG.random(n) * 3])
    rgb = RNG.integers(0, 65536, (n, 3)).astype(np.uint16)
    scales, offsets = (0.001, 0.002, 0.0005), (1000.0, 2000.0, 10.0)
    write_las(tmp_path / "site.las", xyz, rgb, RNG.integers(0, 65536, n), scales, offsets)
    write_las(tmp_path / "site.laz", xyz, rgb, RNG.integers(0, 65536, n), scales, offsets)
    las, laz = load_scan(tmp_path / "site.las"), load_scan(tmp_path / "site.laz")
    s, o = np.array(scales), np.array(offsets)
    stored = np.round((xyz - o) / s) * s + o  # the LAS integers times scale plus offset
    np.testing.assert_allclose(las.points, stored, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(las.colors, np.rint(rgb * (255 / 65535)).astype(np.uint8))
    assert las.source["format"] == "las" and laz.source["format"] == "laz"
    assert las.source["scales"] == list(scales) and las.source["rgb_bits"] == 16
    np.testing.assert_array_equal(laz.points, las.points)
    np.testing.assert_array_equal(laz.colors, las.colors)
    assert laz.source["sha256"] == hashlib.sha256((tmp_path / "site.laz").read_bytes()).hexdigest()
    assert las.units == "unknown" and las.source["crs"] is None


def test_las_eight_bit_colours_and_no_colour(tmp_path):
    xyz = random_cloud(200, 10.0)
    rgb = RNG.integers(0, 256, (200, 3)).astype(np.uint16)
    write_las(tmp_path / "eight.las", xyz, rgb, offsets=(0, 0, 0))
    scan = load_scan(tmp_path / "eight.las")
    np.testing.assert_array_equal(scan.colors, rgb.astype(np.uint8))
    assert scan.source["rgb_bits"] == 8
    write_las(tmp_path / "grey.las", xyz, offsets=(0, 0, 0))
    assert load_scan(tmp_path / "grey.las").colors is None


US_FOOT_WKT = (
    'PROJCS["NAD83 / Texas Central (ftUS)",GEOGCS["NAD83",DATUM["North_American_Datum_1983",'
    'SPHEROID["GRS 1980",6378137,298.257222101]],PRIMEM["Greenwich",0],'
    'UNIT["degree",0.0174532925199433]],PROJECTION["Lambert_Conformal_Conic_2SP"],'
    'PARAMETER["standard_parallel_1",31.8833333333333],UNIT["US survey foot",'
    '0.304800609601219,AUTHORITY["EPSG","9003"]],AXIS["Easting",EAST],AXIS["Northing",NORTH],'
    'AUTHORITY["EPSG","2277"]]')
WKT2_METRE = (
    'PROJCRS["ETRS89 / UTM zone 33N",BASEGEOGCRS["ETRS89",DATUM["European Terrestrial '
    'Reference System 1989",ELLIPSOID["GRS 1980",6378137,298.257222101,LENGTHUNIT["metre",1]]],'
    'ANGLEUNIT["degree",0.0174532925199433]],CONVERSION["UTM zone 33N",METHOD["Transverse '
    'Mercator"]],CS[Cartesian,2],AXIS["easting (E)",east,LENGTHUNIT["metre",1]],'
    'AXIS["northing (N)",north,LENGTHUNIT["metre",1]],ID["EPSG",25833]]')


def test_las_units_from_the_crs(tmp_path):
    xyz = random_cloud(100, 5.0)
    write_las(tmp_path / "feet.las", xyz, offsets=(0, 0, 0),
              vlrs=[WktCoordinateSystemVlr(US_FOOT_WKT)], version="1.4")
    scan = load_scan(tmp_path / "feet.las")
    assert scan.units == "us-ft" and scan.source["crs"]["unit"] == "US survey foot"

    keys = GeoKeyDirectoryVlr()
    keys.geo_keys = [GeoKeyEntryStruct(id=1024, tiff_tag_location=0, count=1, value_offset=1),
                     GeoKeyEntryStruct(id=3072, tiff_tag_location=0, count=1,
                                       value_offset=32633),
                     GeoKeyEntryStruct(id=3076, tiff_tag_location=0, count=1, value_offset=9001)]
    keys.geo_keys_header.number_of_keys = 3
    write_las(tmp_path / "metres.laz", xyz, offsets=(0, 0, 0), vlrs=[keys])
    scan = load_scan(tmp_path / "metres.laz")
    assert scan.units == "m" and scan.source["crs"]["epsg"] == 32633

    assert units_of_wkt(WKT2_METRE)[0] == "m"
    units, _, warnings = units_of_wkt('GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",'
                                      '6378137,298.257223563]],UNIT["degree",0.01745]]')
    assert units == "unknown" and "geographic" in warnings[0]
    assert units_of_geo_keys({1024: 1, 3076: 9002})[0] == "ft"
    assert units_of_geo_keys({1024: 1, 3072: 2277})[0] == "unknown"
    assert parse_wkt('UNIT["a ""b""",1]') == ("UNIT", ['a "b"', 1.0])
    with pytest.raises(ValueError, match="never closed"):
        parse_wkt('PROJCS["x",UNIT["m",1]')


def test_las_fit_from_the_command_line(tmp_path):
    points = relief_scan(4_000, seed=9) / 1000.0
    write_las(tmp_path / "relief.laz", points, offsets=(0.25, -0.04, 1.2),
              scales=(1e-5, 1e-5, 1e-5))
    assert tessera(["fit", str(tmp_path / "relief.laz"), "-o", str(tmp_path / "b"),
                    "--grid", "8x8", "-q"]) == 0
    manifest = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert manifest["provenance"]["format"] == "laz"
    assert manifest["provenance"]["points"] == 4_000


def test_las_bad_files(tmp_path):
    xyz = random_cloud(5_000, 10.0)
    write_las(tmp_path / "good.las", xyz, offsets=(0, 0, 0))
    write_las(tmp_path / "good.laz", xyz, offsets=(0, 0, 0))
    las, laz = (tmp_path / "good.las").read_bytes(), (tmp_path / "good.laz").read_bytes()

    bad = tmp_path / "bad.las"
    bad.write_bytes(b"LASX" + las[4:])
    with pytest.raises(ScanError, match=r"bad\.las: not a LAS/LAZ file: it starts with "
                                        r"b'LASX'"):
        load_scan(bad)

    for cut in (len(laz) // 2, 400):
        truncated = tmp_path / "truncated.laz"
        truncated.write_bytes(laz[:cut])
        with pytest.raises(ScanError, match=r"truncated\.laz: corrupt or truncated LAZ file"):
            load_scan(truncated)

    # a chunk table whose count would have lazrs allocate 64 GB (it aborted the process)
    with laspy.open(str(tmp_path / "good.laz")) as reader:
        start = reader.header.offset_to_point_data
    table = struct.unpack_from("<q", laz, start)[0]
    huge = bytearray(laz)
    struct.pack_into("<I", huge, table + 4, 4_000_000_000)
    (tmp_path / "chunks.laz").write_bytes(bytes(huge))
    with pytest.raises(ScanError, match=r"chunks\.laz: corrupt LAZ file: its chunk table "
                                        "counts 4,000,000,000 chunks, more than the 1"):
        load_scan(tmp_path / "chunks.laz")
    astray = bytearray(laz)
    struct.pack_into("<q", astray, start, 1 << 40)
    (tmp_path / "astray.laz").write_bytes(bytes(astray))
    with pytest.raises(ScanError, match=r"astray\.laz: corrupt or truncated LAZ file: its "
                                        "chunk table offset 1,099,511,627,776 lies outside"):
        load_scan(tmp_path / "astray.laz")

    short = tmp_path / "short.las"
    short.write_bytes(las[:len(las) - 1000])
    with pytest.raises(ScanError, match=r"short\.las: truncated LAS file: the header claims "
                                        "5,000 points"):
        load_scan(short)

    tiny = tmp_path / "tiny.las"
    tiny.write_bytes(las[:50])
    with pytest.raises(ScanError, match=r"tiny\.las: corrupt or truncated LAS file"):
        load_scan(tiny)

    with pytest.raises(ScanError, match=r"good\.laz: 5,000 points, over the limit "
                                        r"max_points = 4,999.*--max-points"):
        load_scan(tmp_path / "good.laz", limits=InputLimits(max_points=4_999))

    empty = tmp_path / "empty.las"
    laspy.LasData(laspy.LasHeader(point_format=1, version="1.2")).write(str(empty))
    with pytest.raises(ScanError, match=r"empty\.las: the file contains no points"):
        load_scan(empty)

    zipped = tmp_path / "good.las.gz"
    zipped.write_bytes(gzip.compress(las))
    with pytest.raises(ScanError, match=r"good\.las\.gz: a gzip-compressed LAS file"):
        load_scan(zipped)


# ----------------------------------------------------------------------------- uploads
def test_uploads_sniff_scanner_formats(tmp_path):
    write_e57(tmp_path / "a.e57", [{"xyz": random_cloud(50)}])
    write_las(tmp_path / "a.las", random_cloud(50), offsets=(0, 0, 0))
    write_las(tmp_path / "a.laz", random_cloud(50), offsets=(0, 0, 0))
    for ext in (".e57", ".las", ".laz"):
        path = tmp_path / f"a{ext}"
        head = path.read_bytes()[:1 << 16]
        assert sniff_format(head, path.stat().st_size, "upload.bin") == ext
        received = tmp_path / f"received{ext}"
        received.write_bytes(path.read_bytes())
        prepared = prepare_scan(ReceivedFile(received, "mine.bin", received.stat().st_size,
                                             ""), UploadLimits())
        assert prepared.scan_path.name == f"scan{ext}"
        assert load_scan(prepared.scan_path).n_points == 50
    zipped = tmp_path / "upload"
    zipped.write_bytes(gzip.compress((tmp_path / "a.e57").read_bytes()))
    with pytest.raises(UploadError, match=r"x\.e57\.gz: a gzip-compressed \.e57 is not read"):
        prepare_scan(ReceivedFile(zipped, "x.e57.gz", zipped.stat().st_size, ""),
                     UploadLimits())
