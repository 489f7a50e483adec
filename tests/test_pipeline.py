"""``tessera fit`` end to end: bundles, scan coordinates, determinism, bad input, real scans."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from client_py import read_patch, tessellate_grid
from fitter.cli import main as tessera
from fitter.demo import write_scan_ply
from fitter.fitting.examples import relief_scan
from fitter.fitting.io import ScanError, load_scan
from fitter.fitting.pipeline import FitOptions, fit_scan


@pytest.fixture(scope="module")
def relief_bundle(tmp_path_factory):
    root = tmp_path_factory.mktemp("fit")
    scan = root / "relief.ply"
    write_scan_ply(scan, relief_scan(20_000, seed=4))
    status = tessera(["fit", str(scan), "-o", str(root / "bundle"), "--grid", "20x20", "-q"])
    assert status == 0
    return root, scan


def test_bundle_contents_and_manifest(relief_bundle):
    root, scan = relief_bundle
    bundle = root / "bundle"
    manifest = json.loads((bundle / "manifest.json").read_text())
    for name in ("base.tsp", "error.png", "error.ply"):
        assert manifest["files"][name] == (bundle / name).stat().st_size > 0
    assert manifest["format_version"] == 1 and manifest["units"] == "mm"
    assert manifest["provenance"]["points"] == 20_000
    assert manifest["provenance"]["bytes"] == scan.stat().st_size
    assert manifest["projection"]["kind"] == "plane"
    stats = manifest["stats"]
    assert 0 < stats["rms"] <= stats["p99"] <= stats["max"]
    assert stats["rms"] < 0.003 * stats["bbox_diagonal"]
    grid = manifest["error_grid"]
    assert len(grid["values"]) == grid["rows"] * grid["cols"]
    error_ply = trimesh.load(bundle / "error.ply", process=False)
    assert len(error_ply.vertices) == 20_000


def test_tessellated_patch_lies_on_the_scan_in_scan_coordinates(relief_bundle, tmp_path):
    root, scan = relief_bundle
    assert tessera(["tessellate", str(root / "bundle"), "-o", str(tmp_path / "m.ply"),
                    "--resolution", "64"]) == 0
    mesh = trimesh.load(tmp_path / "m.ply", process=False)
    points = load_scan(scan).points
    dist, _ = cKDTree(points).query(mesh.vertices)
    # every vertex of the patch is within a few scan spacings of a scan point
    assert np.percentile(dist, 95) < 3.0 and dist.max() < 6.0


def test_same_input_same_bytes(tmp_path):
    points = relief_scan(5_000, seed=2)
    options = FitOptions(grid=(10, 10))
    a = fit_scan(points, tmp_path / "a", options)
    b = fit_scan(points, tmp_path / "b", options)
    for name in ("base.tsp", "error.ply", "error.png"):
        assert (a.path / name).read_bytes() == (b.path / name).read_bytes()
    a.manifest.pop("timings"), b.manifest.pop("timings")
    assert a.manifest == b.manifest


def test_refinement_beats_the_papers_linear_fit(tmp_path):
    points = relief_scan(20_000, seed=5)
    linear = fit_scan(points, tmp_path / "l", FitOptions(grid=(30, 30), method="linear"))
    paper = fit_scan(points, tmp_path / "p", FitOptions(grid=(30, 30), method="paper"))
    ours = fit_scan(points, tmp_path / "t", FitOptions(grid=(30, 30)))
    assert paper.manifest["stats"]["rms"] < linear.manifest["stats"]["rms"]
    assert ours.manifest["stats"]["rms"] <= 0.8 * linear.manifest["stats"]["rms"]


def test_max_error_grows_the_grid(tmp_path):
    points = relief_scan(20_000, seed=6)
    coarse = fit_scan(points, tmp_path / "c", FitOptions(grid=(8, 8), method="linear"))
    target = 0.6 * coarse.manifest["stats"]["rms"]
    grown = fit_scan(points, tmp_path / "g",
                     FitOptions(grid=(8, 8), method="linear", max_error=target, max_grid=40))
    assert grown.manifest["base"]["grid"][0] > 8
    assert grown.manifest["stats"]["rms"] <= target


def test_wrapped_object_uses_a_cylinder_with_a_closed_seam(tmp_path):
    rng = np.random.default_rng(3)
    n = 30_000
    theta, z = rng.uniform(-np.pi, np.pi, n), rng.uniform(0, 300, n)
    r = 80 + 6 * np.cos(3 * theta) + 10 * np.sin(z / 60)
    points = np.column_stack([r * np.cos(theta), r * np.sin(theta), z])
    bundle = fit_scan(points, tmp_path / "cyl", FitOptions(grid=(24, 16)))
    manifest = bundle.manifest
    assert manifest["projection"]["kind"] == "cylinder"
    assert manifest["projection"]["coverage"] > 0.95
    assert manifest["stats"]["rms"] < 0.5
    surface = read_patch((bundle.path / "base.tsp").read_bytes())
    for v in (0.2, 0.5, 0.8):
        p0, du0, _ = surface.derivatives(0.0, v)
        p1, du1, _ = surface.derivatives(1.0, v)
        np.testing.assert_allclose(p0, p1, atol=1e-9)
        # C1 up to the 16-bit quantisation of the control points
        np.testing.assert_allclose(du0, du1, atol=1e-3 * np.linalg.norm(du0))
    mesh = tessellate_grid(surface, 16, 16)
    assert mesh.vertex_count == 256


@pytest.mark.parametrize(
    "points, message",
    [
        (np.full((100, 3), np.nan), "non-finite"),
        (np.zeros((0, 3)), "no points"),
        (relief_scan(30), "at least 64"),
        (np.ones((500, 3)), "coincide"),
    ],
)
def test_bad_scans_give_one_clear_error(tmp_path, points, message):
    with pytest.raises(ScanError, match=message):
        fit_scan(points, tmp_path / "x", FitOptions(grid=(8, 8)))
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    "options, message",
    [
        (FitOptions(grid=(2, 40)), "grid"),
        (FitOptions(method="magic"), "method"),
        (FitOptions(bits=40), "bits"),
        (FitOptions(max_error=-1.0), "max_error"),
        (FitOptions(projection="torus"), "projection"),
        (FitOptions(degree=0), "degree"),
        (FitOptions(samples=10), "samples"),
    ],
)
def test_bad_options_give_one_clear_error(tmp_path, options, message):
    with pytest.raises(ValueError, match=message):
        fit_scan(relief_scan(1000), tmp_path / "x", options)


def test_automatic_bits_cost_at_most_a_percent_of_rms(tmp_path):
    """The default quantisation picks fewer bits than 16 and keeps the RMS (measured on the
    decoded patch) within 1 % of the 16-bit patch's, for fewer bytes."""
    scan = relief_scan(20000)
    auto = fit_scan(scan, tmp_path / "auto", FitOptions(grid=(20, 20))).manifest
    fixed = fit_scan(scan, tmp_path / "fixed", FitOptions(grid=(20, 20), bits=16)).manifest
    assert 8 <= auto["base"]["bits"] < 16 == fixed["base"]["bits"]
    assert auto["stats"]["rms"] <= 1.01 * fixed["stats"]["rms"]
    assert auto["files"]["base.tsp"] < fixed["files"]["base.tsp"]


def test_conf_provenance_lists_every_file_with_its_digest(tmp_path):
    points = relief_scan(6000)
    lines = []
    for i, part in enumerate((points[::2], points[1::2])):
        np.savetxt(tmp_path / f"part{i}.xyz", part, fmt="%.9g")
        lines.append(f"bmesh part{i}.xyz 0 0 0 0 0 0 1")
    (tmp_path / "all.conf").write_text("\n".join(lines) + "\n")
    manifest = fit_scan(tmp_path / "all.conf", tmp_path / "b", FitOptions(grid=(12, 12))).manifest
    files = {f["name"]: f for f in manifest["provenance"]["files"]}
    assert set(files) == {"all.conf", "part0.xyz", "part1.xyz"}
    for name, entry in files.items():
        data = (tmp_path / name).read_bytes()
        assert entry["sha256"] == hashlib.sha256(data).hexdigest()
        assert entry["bytes"] == len(data)
    assert manifest["provenance"]["points"] == len(points)


def test_cli_reports_bad_input_without_traceback(tmp_path, capsys):
    bad = tmp_path / "bad.xyz"
    bad.write_text("1 2 nan\n3 4 5\n")
    assert tessera(["fit", str(bad), "-o", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "non-finite" in err and "Traceback" not in err
    assert tessera(["fit", str(tmp_path / "missing.ply"), "-o", str(tmp_path / "o")]) == 2


@pytest.mark.realdata
@pytest.mark.parametrize("relative", ["happy-buddha-rangescans/happyStandRight_0.ply.gz",
                                      "bali-mask/mask.obj"])
def test_real_scan_fits_better_than_the_papers_linear_fit(shared_data, tmp_path, relative):
    scan = load_scan(shared_data / relative)
    linear = fit_scan(scan, tmp_path / "linear", FitOptions(method="linear"))
    ours = fit_scan(scan, tmp_path / "ours", FitOptions())
    assert ours.manifest["stats"]["rms"] <= 0.8 * linear.manifest["stats"]["rms"]
    assert ours.manifest["projection"]["coverage"] > 0.5
    # the patch is in the scan's coordinates: its vertices lie near scan points
    surface = read_patch((ours.path / "base.tsp").read_bytes()).to_scan_frame()
    mesh = tessellate_grid(surface, 48, 48)
    vertices = np.frombuffer(mesh.positions, dtype=np.float32).reshape(-1, 3)
    used = np.unique(np.frombuffer(mesh.indices, dtype=np.uint32))
    dist, _ = cKDTree(scan.points).query(vertices[used])
    assert np.median(dist) < 0.01 * ours.manifest["stats"]["bbox_diagonal"]
