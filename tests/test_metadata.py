"""An object's metadata from the command line to the manifest (title, description, units:
one table, ``fitter.fitting.options``), the units a file states (OBJ comments), and the
manifest's error raster (``fitter.fitting.error.error_raster``) against an independent
per-cell maximum."""

from __future__ import annotations

import json
import zlib

import numpy as np
import pytest

from fitter.cli import build_parser, main
from fitter.demo import write_scan_ply
from fitter.fitting.error import Deviations, error_raster
from fitter.fitting.examples import relief_scan
from fitter.fitting.io import load_scan
from fitter.fitting.options import FitOptions, from_args, stored_options

DESCRIPTION = "A carved limestone relief.\nSecond line: found in 1911."


@pytest.fixture(scope="module")
def labelled_bundle(tmp_path_factory):
    root = tmp_path_factory.mktemp("meta")
    scan = root / "relief.ply"
    write_scan_ply(scan, relief_scan(6_000, seed=3))  # its header says "units mm"
    argv = ["fit", str(scan), "-o", str(root / "b"), "--grid", "10x10", "-q",
            "--detail-levels", "0", "--title", "Relief of a long title that wraps",
            "--description", DESCRIPTION, "--units", "cm"]
    assert main(argv) == 0
    return json.loads((root / "b" / "manifest.json").read_text()), argv


def test_cli_to_fit_options_to_manifest(labelled_bundle):
    manifest, argv = labelled_bundle
    options = from_args(build_parser().parse_args(argv))
    assert (options.title, options.description, options.units) == (
        "Relief of a long title that wraps", DESCRIPTION, "cm")
    assert manifest["title"] == "Relief of a long title that wraps"
    assert manifest["description"] == DESCRIPTION
    # the option overrides the file's "units mm", everywhere the bundle names a unit
    assert manifest["units"] == manifest["stats"]["units"] == "cm"
    assert manifest["options"] == stored_options(options)


def test_without_the_options_the_file_says_the_units_and_there_is_no_description(tmp_path):
    scan = tmp_path / "relief.ply"
    write_scan_ply(scan, relief_scan(4_000, seed=1))
    assert main(["fit", str(scan), "-o", str(tmp_path / "b"), "--grid", "8x8", "-q",
                 "--detail-levels", "0"]) == 0
    manifest = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert manifest["units"] == "mm" and manifest["description"] == ""
    assert manifest["title"] == "relief.ply"


def test_fit_collection_has_no_per_object_options(capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["fit-collection", "s.ply", "-o", "o", "--title", "x"])
    assert exc.value.code == 2 and "--title" in capsys.readouterr().err
    args = build_parser().parse_args(["fit-collection", "s.ply", "-o", "o", "--units", "mm"])
    assert from_args(args).units == "mm" and from_args(args).title is None


@pytest.mark.parametrize("name, value, match", [
    ("units", "x" * 21, "units must be text of at most 20 characters"),
    ("units", "m\nm", "units must be text of at most 20 characters on one line"),
    ("title", "t" * 201, "title must be text of at most 200 characters"),
    ("description", "d" * 10_001, "description must be text of at most 10000 characters"),
])
def test_metadata_options_are_refused_naming_the_option(name, value, match):
    with pytest.raises(ValueError, match=match):
        FitOptions(**{name: value}).validate()


def test_obj_header_comment_gives_the_units(tmp_path):
    obj = tmp_path / "tri.obj"
    obj.write_text("# exported by a scanner\n# units: millimetres\n"
                   "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0.5\nf 1 2 3\nf 2 4 3\n")
    assert load_scan(obj).units == "mm"
    plain = tmp_path / "plain.obj"
    plain.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n# units m (after the first statement)\nf 1 2 3\n")
    assert load_scan(plain).units == "unknown"


def test_gltf_is_metres_by_its_specification(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    mesh = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    path = tmp_path / "tri.glb"
    mesh.export(path)
    assert load_scan(path).units == "m"


# ------------------------------------------------------------------- the error raster
def _cell_maxima(dev: Deviations, side: int) -> dict[tuple[int, int], float]:
    """The largest |d| per cell, point by point (an independent reference)."""
    largest: dict[tuple[int, int], float] = {}
    for d, u, v in zip(dev.d, dev.u, dev.v, strict=True):
        key = (min(int(u * side), side - 1), min(int(v * side), side - 1))
        largest[key] = max(largest.get(key, 0.0), abs(float(d)))
    return largest


def test_error_raster_is_the_largest_deviation_per_cell_and_ends_at_the_max():
    rng = np.random.default_rng(7)
    n = 9_000
    u, v = rng.random(n), rng.random(n)
    keep = (u - 0.5) ** 2 + (v - 0.5) ** 2 > 0.02  # a hole in the middle
    dev = Deviations(rng.normal(0, 0.1, n)[keep], u[keep], v[keep])
    dev.d[17] = 3.0  # a spike
    top = float(np.abs(dev.d).max())
    raster, data = error_raster(dev, top)
    side = raster["rows"]
    assert side == raster["cols"] == int(np.sqrt(keep.sum() / 4))
    assert raster["file"] == "error_raster.bin" and raster["bytes"] == len(data)
    assert "data" not in raster  # the codes are the file's, not the manifest's (session 17)
    codes = np.frombuffer(zlib.decompress(data), np.uint8).reshape(side, side)
    reference = _cell_maxima(dev, side)
    for i in range(side):
        for j in range(side):
            if (i, j) in reference:
                assert abs(codes[i, j] / 254 * top - reference[i, j]) <= top / 254 / 2 + 1e-12
            else:
                assert codes[i, j] == 255
    assert codes[side // 2, side // 2] == 255  # the hole
    assert raster["max"] == top and codes.max(initial=0, where=codes < 255) == 254


def test_error_raster_side_is_bounded():
    few = Deviations(np.array([0.1, 0.2]), np.array([0.1, 0.9]), np.array([0.1, 0.9]))
    assert error_raster(few, 0.2)[0]["rows"] == 8
    many = Deviations(np.zeros(100_000), np.linspace(0, 1, 100_000), np.linspace(0, 1, 100_000))
    flat, data = error_raster(many, 0.0)
    assert flat["rows"] == 64
    assert set(zlib.decompress(data)) <= {0, 255}
