"""A scan far from the origin is fitted moved near it; one too small or too large is refused
(``fitter.fitting.io.frame``)."""

from __future__ import annotations

import copy
import io
import pickle
import re
from pathlib import Path

import numpy as np
import pytest

from fitter.fitting.io.frame import FAR, SIZES, moved, near_origin, scan_origin
from fitter.fitting.io.points import PointStream, ReaderStream
from fitter.fitting.io.scan import Scan, ScanError


def test_a_scan_near_the_origin_is_not_moved():
    lo, hi = np.array([-1.0, 2.0, 0.0]), np.array([1.0, 4.0, 1.0])
    assert scan_origin("s", lo, hi) is None
    diagonal = np.linalg.norm(hi - lo)
    assert scan_origin("s", lo + FAR * diagonal / 2, hi + FAR * diagonal / 2) is None
    assert scan_origin("s", np.zeros(3), np.zeros(3)) is None  # refused as coincident later
    scan = Scan.from_array(np.random.default_rng(0).random((100, 3)))
    assert near_origin(scan) is scan


def test_a_far_scan_is_moved_by_its_centre_rounded_to_a_readable_number():
    # a unit sphere's box in UTM coordinates: diagonal 3.46, rounded to units
    lo = np.array([5e6 - 1.0 + 0.0213, 4e6 - 1.0, 299.0])
    hi = lo + 2.0
    assert scan_origin("s", lo, hi).tolist() == [5000000.0, 4000000.0, 300.0]
    # a 30 cm object in millimetres 20 km from the origin: rounded to 100 mm
    origin = scan_origin("s", np.array([2e7 + 11.0, 0.0, 0.0]),
                         np.array([2e7 + 311.0, 290.0, 280.0]))
    assert origin.tolist() == [20000200.0, 100.0, 100.0]
    # a 30 cm object in metres, 1,235 km out: to the decimetre, as written
    origin = scan_origin("s", np.array([1234567.891 - 0.1, 0.0, 0.0]),
                         np.array([1234567.891 + 0.1, 0.2, 0.1]))
    assert [repr(float(x)) for x in origin] == ["1234567.9", "0.1", "0.0"]
    points = np.array([[5e6 + 0.5, 4e6 - 0.25, 300.125], [5e6 - 0.5, 4e6 + 0.75, 299.0]])
    scan = Scan.from_array(points)
    near = near_origin(scan)
    assert near.source["origin"] == [5e6, 4e6, 300.0]
    assert np.array_equal(near.points, [[0.5, -0.25, 0.125], [-0.5, 0.75, -1.0]])
    assert "origin" not in scan.source and moved(scan, None) is scan


@pytest.mark.parametrize("size", [1e-30, 1e-7, 1e11, 1e30])
def test_a_scan_too_small_or_too_large_is_refused_naming_its_diagonal(size):
    with pytest.raises(ScanError, match=re.escape(
            f"s: the scan's bounding box has a diagonal of {size * 3 ** 0.5:.3g} units; a fit "
            "takes 1e-06..1e+10")):
        scan_origin("s", np.zeros(3), np.full(3, size))
    assert SIZES == (1e-6, 1e10)


def test_a_stream_reads_its_points_moved():
    points = np.array([[1e6, 0.0, 0.0], [1e6 + 1.0, 2.0, 3.0], [1e6 + 0.5, 1.0, 1.0]])
    stream = PointStream.from_arrays("s", points)
    stream.origin = np.array([1e6, 1.0, 0.0])
    expected = points - stream.origin
    assert np.array_equal(stream.read(0, 3)[0], expected)
    assert np.array_equal(stream.take(np.array([0, 2]))[0], expected[[0, 2]])


class _Blocks(ReaderStream):
    """A reader stream (as an E57's or a LAS file's) decoding blocks of 7 points."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = points
        super().__init__("blocks", Path("blocks"), [len(points)])

    def open_file(self) -> object:
        return io.BytesIO()

    def open_segment(self, segment: int, first: int):  # noqa: ANN201 - (int, iterator)
        return 0, iter([self.points[i:i + 7] for i in range(0, len(self.points), 7)])


def test_a_reader_stream_reads_its_points_moved_in_every_process():
    points = np.random.default_rng(0).random((50, 3)) + 1e6
    stream = _Blocks(points)
    stream.origin = np.array([1e6, 1e6, 1e6])
    expected = points - stream.origin
    for copied in (stream, copy.copy(stream), pickle.loads(pickle.dumps(stream))):  # Dask's
        assert np.array_equal(copied.read(0, 50)[0], expected)
        assert np.array_equal(copied.take(np.array([3, 30]))[0], expected[[3, 30]])


def test_the_clients_origin_is_the_manifests_and_a_bad_one_is_named():
    from client_py.bundle import ManifestError, scan_origin

    assert scan_origin({"provenance": {"points": 3}}) is None
    assert scan_origin({}) is None
    assert scan_origin({"provenance": {"origin": [5e6, 4e6, 300]}}) == [5e6, 4e6, 300.0]
    for bad in ([1, 2], [1, 2, float("nan")], "0 0 0", [1, 2, True]):
        with pytest.raises(ManifestError, match="provenance.origin"):
            scan_origin({"provenance": {"origin": bad}})


def test_a_far_scan_in_single_precision_is_warned_of():
    """Moving cannot restore bits the file lost: far float32 coordinates are named, with
    the step they hold; double, whole-number or near coordinates are not."""
    from fitter.fitting.io.frame import single_precision_warning

    unit = np.random.default_rng(1).normal(size=(500, 3))
    unit /= np.linalg.norm(unit, axis=1)[:, None]
    offset = np.array([5e6, 4e6, 300.0])
    single = (unit + offset).astype(np.float32).astype(np.float64)
    scan = near_origin(Scan.from_array(single))
    assert scan.source["origin"] == [5e6, 4e6, 300.0]
    assert scan.source["warnings"] == [
        "the coordinates are single precision 5e+06 units from 0: the file holds them to "
        f"about 0.5 units, {100 * 0.5 / np.linalg.norm(np.ptp(single, axis=0)):.2g} % of "
        "the scan's diagonal (write them in double precision, or nearer the origin)"]
    assert near_origin(Scan.from_array(unit + offset)).source["warnings"] == []  # double
    whole = np.round(unit * 1000) + offset  # millimetres on a whole-number grid
    assert single_precision_warning(whole, offset, 3464.0) is None
    near = (unit + 50.0).astype(np.float32).astype(np.float64)  # a step of 4e-6: fine
    assert single_precision_warning(near, np.full(3, 50.0), 3.46) is None
