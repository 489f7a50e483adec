"""E57 and LAS/LAZ read block by block for the out-of-core fit (issue 16): the streams give the
points their whole-file loaders give, bit for bit and in order, whatever the read order;
a streamed fit gives the bundle of the same cloud as binary PLY (E57) or as loaded arrays.

The files are written by pye57 and laspy (the writers of ``tests/test_readers_scanner.py``).
"""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import fitter.fitting.io.e57 as e57_io
import fitter.fitting.io.las as las_io
import fitter.fitting.io.points as points_io
import fitter.fitting.stream as stream
from client_py.ply import write_points_ply
from fitter.fitting.examples import relief_scan
from fitter.fitting.io import InputLimits, ScanError, load_scan, open_point_stream
from fitter.fitting.io.e57 import E57Stream, open_e57_stream
from fitter.fitting.io.las import LasStream, open_las_stream
from fitter.fitting.io.limits import InputBudget
from fitter.fitting.options import FitOptions
from fitter.fitting.pipeline import fit_scan
from tests.test_out_of_core import small_out_of_core  # noqa: F401 (a fixture)
from tests.test_readers_scanner import write_e57, write_las, write_spherical_e57

RNG = np.random.default_rng(57)
OPTIONS = dict(grid=(12, 12), samples=5_000, detail_levels=1, texture=False)


@pytest.fixture
def small_blocks(monkeypatch):
    """Readers' blocks of 64 points, so a scan of hundreds of points spans several."""
    monkeypatch.setattr(e57_io, "BLOCK_POINTS", 64)
    monkeypatch.setattr(las_io, "BLOCK_POINTS", 64)
    monkeypatch.setattr(points_io, "TAKE_BLOCK", 100)
    monkeypatch.setattr(points_io, "WINDOW_REQUESTS", 2)


def _posed_site(path):
    """Three posed scans with colour and intensity; the first and last with invalid points
    (the last all invalid but one), the middle one empty of invalid-state fields."""
    scans = []
    for k, n in enumerate((700, 450, 300)):
        q = Rotation.from_euler("xyz", RNG.uniform(-90, 90, 3), degrees=True).as_quat()
        scan = {"xyz": RNG.uniform(-2, 2, (n, 3)), "name": f"station {k}",
                "rgb": RNG.integers(0, 256, (n, 3), dtype=np.uint8),
                "intensity": RNG.random(n), "rotation": [q[3], *q[:3]],
                "translation": RNG.uniform(-10, 10, 3)}
        if k != 1:
            invalid = (RNG.random(n) < 0.25).astype(np.int8) * 2
            if k == 2:
                invalid[:] = 1
                invalid[150] = 0
            scan["invalid"] = invalid
        scans.append(scan)
    write_e57(path, scans)


def _read_in_blocks(pstream, size, order=None):
    """The stream read in blocks of ``size`` points, in ``order`` (default: in order; or
    "pairs": 1, 0, 3, 2, ..., as two threads may ask), put back in order."""
    blocks = pstream.blocks(size)
    k = len(blocks)
    if order is None:
        order = range(k)
    elif order == "pairs":
        order = [i ^ 1 if (i ^ 1) < k else i for i in range(k)]
    parts = {i: pstream.read(*blocks[i])[0] for i in order}
    assert sorted(parts) == list(range(k))
    return np.concatenate([parts[i] for i in range(k)])


def test_e57_stream_gives_the_points_of_load_e57_in_any_order(tmp_path, small_blocks):
    path = tmp_path / "site.e57"
    _posed_site(path)
    loaded = load_scan(path).points
    opened = open_e57_stream(path)
    assert opened is not None
    pstream, source, units = opened
    assert isinstance(pstream, E57Stream) and units == "m" and not pstream.has_normals
    assert pstream.count == len(loaded) and pstream.segments[1] == 450 and pstream.segments[2] == 1
    assert [s["points"] for s in source["scans"]] == list(pstream.segments)
    assert source["scans"][1]["invalid_dropped"] is None and source["sha256"] is None
    # in block order every point is decoded once
    np.testing.assert_array_equal(_read_in_blocks(pstream, 97), loaded)
    assert pstream.decoded == pstream.count and not pstream._window  # all handed out
    # two threads' order (one block ahead) is served from the window, no point decoded twice
    fresh = open_e57_stream(path)[0]
    np.testing.assert_array_equal(_read_in_blocks(fresh, 97, "pairs"), loaded)
    assert fresh.decoded == fresh.count
    # the same across scans: the end of scan 0 asked for after the start of scan 1
    across = open_e57_stream(path)[0]
    s1 = across.segments[0]
    for start in (s1 - 300, s1, s1 - 150):
        np.testing.assert_array_equal(across.read(start, start + 150)[0],
                                      loaded[start:start + 150])
    assert across.decoded == s1 + 192  # scan 0 once, scan 1 to its third block of 64
    # backward past the window: the scan is decoded again from its start
    np.testing.assert_array_equal(fresh.read(3, 40)[0], loaded[3:40])
    assert fresh.decoded > fresh.count
    index = np.sort(RNG.choice(len(loaded), 60, replace=False))
    np.testing.assert_array_equal(fresh.take(index)[0], loaded[index])
    # a pickled stream (a Dask worker's) leaves its file and window behind and reopens
    again = pickle.loads(pickle.dumps(fresh))
    assert again._file is None and again.decoded == 0
    np.testing.assert_array_equal(again.read(600, 700)[0], loaded[600:700])
    fresh.close()
    np.testing.assert_array_equal(fresh.read(0, 5)[0], loaded[:5])
    with pytest.raises(IndexError, match=r"site\.e57: points \[0, 9999\) outside"):
        fresh.read(0, 9_999)


def test_e57_stream_of_a_spherical_scan(tmp_path, small_blocks):
    n = 500
    rae = np.column_stack([RNG.uniform(1, 20, n), RNG.uniform(-np.pi, np.pi, n),
                           RNG.uniform(-1.2, 1.2, n)])
    invalid = (RNG.random(n) < 0.2).astype(np.int8) * 2
    q = Rotation.from_euler("xyz", [20, 0, 33], degrees=True).as_quat()
    path = tmp_path / "sphere.e57"
    write_spherical_e57(path, rae, invalid, [q[3], *q[:3]], [5.0, 6.0, 7.0])
    pstream = open_e57_stream(path)[0]
    np.testing.assert_array_equal(_read_in_blocks(pstream, 120, [3, 0, 2, 1]),
                                  load_scan(path).points)


def test_e57_stream_opening_keeps_the_limits_and_errors(tmp_path):
    path = tmp_path / "site.e57"
    _posed_site(path)
    claimed = 700 + 450 + 300
    assert open_e57_stream(path, stream_above=claimed) is None  # read whole instead
    assert open_e57_stream(path, stream_above=claimed - 1) is not None
    with pytest.raises(ScanError, match=r"site\.e57: 1,450 points, over the limit "
                                        "max_points = 1,000"):
        open_point_stream(path, InputBudget(InputLimits(max_points=1_000)))
    truncated = tmp_path / "cut.e57"
    truncated.write_bytes(path.read_bytes()[:5_000])
    with pytest.raises(ScanError, match=r"cut\.e57: truncated E57 file"):
        open_point_stream(truncated)
    all_invalid = tmp_path / "invalid.e57"
    write_spherical_e57(all_invalid, RNG.uniform(1, 2, (30, 3)), np.full(30, 2, np.int8),
                        [1.0, 0, 0, 0], [0.0, 0, 0])
    with pytest.raises(ScanError, match=r"invalid\.e57: the file contains no points: all 30"):
        open_point_stream(all_invalid)
    # a file whose pages are garbled after the headers: the passes name the file
    good = tmp_path / "good.e57"
    write_e57(good, [{"xyz": RNG.uniform(-1, 1, (4_000, 3))}])
    body = bytearray(good.read_bytes())
    body[2048:2048 + 512] = bytes(512)
    (tmp_path / "garbled.e57").write_bytes(bytes(body))
    with pytest.raises(ScanError, match=r"garbled\.e57: corrupt E57 file"):
        opened = open_point_stream(tmp_path / "garbled.e57")
        opened[0].read(0, opened[0].count)


@pytest.mark.usefixtures("small_out_of_core")
def test_streamed_e57_fit_gives_the_bundle_of_the_same_cloud_as_ply(tmp_path):
    points = relief_scan(40_000, seed=11).astype(np.float32)
    colours = RNG.integers(0, 256, (40_000, 3), dtype=np.uint8)
    ply, e57 = tmp_path / "relief.ply", tmp_path / "relief.e57"
    ply.write_bytes(write_points_ply(points, colours, comments=["units m"]))
    write_e57(e57, [{"xyz": points[:25_000].astype(np.float64), "rgb": colours[:25_000]},
                    {"xyz": points[25_000:].astype(np.float64), "rgb": colours[25_000:]}])
    a = fit_scan(ply, tmp_path / "from_ply", FitOptions(**OPTIONS))
    b = fit_scan(e57, tmp_path / "from_e57", FitOptions(**OPTIONS))
    assert (a.path / "base.tsp").read_bytes() == (b.path / "base.tsp").read_bytes()
    ma, mb = (json.loads((x.path / "manifest.json").read_text()) for x in (a, b))
    assert isinstance(stream.open_stream(e57)[0], E57Stream)  # the fit's own dispatch
    assert mb["provenance"]["format"] == "e57" and mb["units"] == "m"
    assert mb["provenance"]["working_set"]["points_before"] == 40_000
    assert mb["stats_all_points"] == ma["stats_all_points"]


def test_las_and_laz_streams_give_the_points_of_load_las(tmp_path, small_blocks):
    n = 1_000
    xyz = np.column_stack([1000 + RNG.random(n) * 50, 2000 + RNG.random(n) * 40,
                           10 + RNG.random(n) * 3])
    rgb = RNG.integers(0, 65536, (n, 3)).astype(np.uint16)
    for name in ("site.las", "site.laz"):
        path = tmp_path / name
        write_las(path, xyz, rgb, RNG.integers(0, 65536, n), (0.001, 0.002, 0.0005))
        loaded = load_scan(path).points
        pstream, source, units = open_las_stream(path)
        assert isinstance(pstream, LasStream) and pstream.count == n
        assert source["format"] == path.suffix[1:] and units == "unknown"
        np.testing.assert_array_equal(_read_in_blocks(pstream, 97), loaded)
        assert pstream.decoded == n
        order = [5, 0, 9, 1, 10, 3, 2, 4, 8, 6, 7]  # back and forth: laspy seeks
        np.testing.assert_array_equal(_read_in_blocks(pstream, 97, order), loaded)
        index = np.sort(RNG.choice(n, 50, replace=False))
        np.testing.assert_array_equal(pstream.take(index)[0], loaded[index])
        again = pickle.loads(pickle.dumps(pstream))
        assert again._file is None
        np.testing.assert_array_equal(again.read(900, 1_000)[0], loaded[900:])
        pstream.close()
    assert open_las_stream(tmp_path / "site.laz", stream_above=n) is None
    with pytest.raises(ScanError, match=r"site\.laz: 1,000 points, over the limit"):
        open_point_stream(tmp_path / "site.laz", InputBudget(InputLimits(max_points=999)))
    laz = (tmp_path / "site.laz").read_bytes()
    (tmp_path / "cut.laz").write_bytes(laz[:len(laz) // 2])
    with pytest.raises(ScanError, match=r"cut\.laz: corrupt or truncated LAZ file"):
        open_point_stream(tmp_path / "cut.laz")
    las = (tmp_path / "site.las").read_bytes()
    (tmp_path / "cut.las").write_bytes(las[:len(las) - 500])
    with pytest.raises(ScanError, match=r"cut\.las: truncated LAS file: the header claims"):
        open_point_stream(tmp_path / "cut.las")


@pytest.mark.usefixtures("small_out_of_core")
def test_streamed_laz_fit_gives_the_bundle_of_the_loaded_cloud(tmp_path):
    points = relief_scan(40_000, seed=13) / 1000.0
    path = tmp_path / "relief.laz"
    write_las(path, points, offsets=(0.25, -0.04, 1.2), scales=(1e-5, 1e-5, 1e-5))
    streamed = fit_scan(path, tmp_path / "streamed", FitOptions(**OPTIONS))
    loaded = fit_scan(load_scan(path), tmp_path / "loaded", FitOptions(**OPTIONS))
    assert isinstance(stream.open_stream(path)[0], LasStream)  # the fit's own dispatch
    assert streamed.manifest["provenance"]["working_set"]["points_before"] == 40_000
    assert ((streamed.path / "base.tsp").read_bytes()
            == (loaded.path / "base.tsp").read_bytes())
    assert streamed.manifest["stats_all_points"] == loaded.manifest["stats_all_points"]


@pytest.mark.usefixtures("small_out_of_core")
def test_e57_stream_on_a_dask_cluster_writes_the_same_bundle(tmp_path):
    distributed = pytest.importorskip("distributed")
    points = relief_scan(40_000, seed=17)
    q = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)
    t = np.array([3.0, -1.0, 0.5])
    path = tmp_path / "posed.e57"  # each scan stored in its own frame, posed back
    write_e57(path, [{"xyz": q.inv().apply(points[:22_000] - t),
                      "rotation": [*q.as_quat()[3:], *q.as_quat()[:3]], "translation": t},
                     {"xyz": points[22_000:]}])
    local = fit_scan(path, tmp_path / "local", FitOptions(**OPTIONS))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        on_dask = fit_scan(path, tmp_path / "dask", FitOptions(**OPTIONS),
                           blocks=stream.DaskBlocks(client))
    assert isinstance(stream.open_stream(path)[0], E57Stream)
    for name in ("base.tsp", "error.ply", "error.png"):
        assert (local.path / name).read_bytes() == (on_dask.path / name).read_bytes(), name
    assert local.manifest["stats_all_points"] == on_dask.manifest["stats_all_points"]
