"""``tessera fit-collection`` on Dask: a 2-worker LocalCluster gives the same bundles as
fitting each scan alone, a re-run fits nothing, a failed scan does not stop the others, and
the command prints its summary table."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fitter.cli import main
from fitter.collection.batch import bundle_name, fit_collection, is_up_to_date
from fitter.demo import write_scan_ply
from fitter.fitting.examples import relief_scan
from fitter.fitting.options import FitOptions
from fitter.fitting.pipeline import fit_scan

OPTIONS = dict(grid=(12, 12), method="linear")


@pytest.fixture(scope="module")
def scans(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three generated reliefs (different seeds and sizes), as binary PLY."""
    folder = tmp_path_factory.mktemp("batch")
    paths = []
    for seed, n in ((0, 8000), (1, 10000), (2, 12000)):
        path = folder / f"relief-{seed}.ply"
        write_scan_ply(path, relief_scan(n, seed=seed))
        paths.append(path)
    return paths


def _same_bundle(a: Path, b: Path) -> None:
    files_a = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b).as_posix() for p in b.rglob("*") if p.is_file())
    assert files_a == files_b
    for name in files_a:
        if name == "manifest.json":
            ma, mb = (json.loads((d / name).read_text()) for d in (a, b))
            ma.pop("timings"), mb.pop("timings")
            assert ma == mb
        else:
            assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_two_dask_workers_give_the_bundles_of_fitting_one_by_one_and_a_rerun_fits_nothing(
        scans, tmp_path):
    """Every file of each bundle is byte-identical to a plain ``fit_scan`` of the same scan,
    and the manifests are equal except ``timings`` (wall-clock seconds, different on every
    run by nature)."""
    options = FitOptions(**OPTIONS)
    out = tmp_path / "collection"
    results = fit_collection(scans, out, options, workers=2, progress=False)
    assert [r.state for r in results] == ["done"] * 3
    assert [Path(r.bundle).name for r in results] == ["relief-0", "relief-1", "relief-2"]
    for scan, result in zip(scans, results, strict=True):
        alone = fit_scan(scan, tmp_path / "alone" / scan.stem, FitOptions(**OPTIONS))
        _same_bundle(Path(result.bundle), alone.path)
        assert result.points == alone.manifest["provenance"]["points"]
        assert result.rms == alone.manifest["stats"]["rms"]
    assert sorted(p.name for p in out.iterdir()) == ["relief-0", "relief-1", "relief-2"]
    mtimes = {p.name: (p / "manifest.json").stat().st_mtime_ns for p in out.iterdir()}

    rerun = fit_collection(scans, out, options, workers=2, progress=False)
    assert [r.state for r in rerun] == ["skipped"] * 3
    assert {p.name: (p / "manifest.json").stat().st_mtime_ns for p in out.iterdir()} == mtimes
    # other options, or another input under the same name, make a bundle stale
    assert not is_up_to_date(out / "relief-0", "0" * 64, options)
    assert not is_up_to_date(out / "relief-0", _sha(scans[0]),
                             FitOptions(grid=(13, 13), method="linear"))
    assert is_up_to_date(out / "relief-0", _sha(scans[0]), options)
    # detail tiles of an older .tsd version make it stale too (this code cannot read them)
    manifest_path = out / "relief-0" / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    assert manifest["tiles"]["detail"]["nodes"]
    manifest["tiles"]["detail"]["format_version"] = 1
    manifest_path.write_text(json.dumps(manifest))
    assert not is_up_to_date(out / "relief-0", _sha(scans[0]), options)


def _sha(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_failed_scan_does_not_stop_the_others_and_the_cli_uses_a_given_scheduler(
        scans, tmp_path, capsys):
    broken = tmp_path / "broken.ply"
    cloud = relief_scan(2000)
    cloud[::5] = np.nan
    write_scan_ply(broken, cloud)
    out = tmp_path / "collection"
    from distributed import LocalCluster

    # an existing scheduler, as a real cluster's (workers are threads here: quick to start)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster:
        status = main(["fit-collection", str(scans[0]), str(broken), "-o", str(out),
                       "--scheduler", cluster.scheduler_address, "--grid", "12x12",
                       "--method", "linear", "-q"])
    assert status == 1  # one scan failed
    table = capsys.readouterr().out
    lines = table.splitlines()
    assert lines[0].split() == ["scan", "points", "bytes", "RMS", "time", "state"]
    assert any(line.startswith("relief-0.ply") and line.rstrip().endswith("done")
               for line in lines)
    assert any(line.startswith("broken.ply") and "failed: " in line and "non-finite" in line
               for line in lines)
    assert "1 fitted, 0 up to date, 1 failed" in table
    assert sorted(p.name for p in out.iterdir()) == ["relief-0"]  # nothing half-written


def test_bundle_names_and_clashes(tmp_path):
    assert bundle_name(Path("a/Happy Buddha_0.ply.gz")) == "Happy-Buddha_0"
    assert bundle_name(Path("x/.hidden.xyz")) == "hidden"
    one, two = tmp_path / "a", tmp_path / "b"
    one.mkdir(), two.mkdir()
    for folder in (one, two):
        (folder / "scan.ply").write_bytes(b"ply\n")
    with pytest.raises(ValueError, match="would both write the bundle 'scan'"):
        fit_collection([one / "scan.ply", two / "scan.ply"], tmp_path / "out",
                       FitOptions(**OPTIONS), progress=False)
    with pytest.raises(ValueError, match="no such scan file"):
        fit_collection([tmp_path / "missing.ply"], tmp_path / "out", FitOptions(**OPTIONS))
