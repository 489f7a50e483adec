"""Input limits (fitter.fitting.io.limits), the memory budget (fitter.fitting.memory) and
degenerate scans (fitter.fitting.degenerate): each hostile or careless input of issue 15
refused with a message naming the file, what is wrong and how to raise the limit.

Inputs are written here: small PLY/XYZ files, gzip streams of repeated rows (bombs),
.conf registrations naming files outside their folder or the same file many times,
zip uploads holding them. Every refusal must come fast and small: the bombs are
checked to be refused within a second and a bounded peak memory (in a subprocess).
"""

from __future__ import annotations

import gzip
import io
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from fitter.collection.uploads import ReceivedFile, UploadError, UploadLimits, prepare_scan
from fitter.fitting.io import InputLimits, ScanError, load_scan
from fitter.fitting.memory import (
    DEFAULT_MEMORY_BUDGET,
    base_fit_bytes,
    detail_level_bytes,
    plan_memory,
)
from fitter.fitting.options import FitOptions, OptionError
from fitter.fitting.pipeline import fit_scan

#: wall-clock bounds below: `make test` runs this file alone, after the parallel part
pytestmark = pytest.mark.timing

ROOT = Path(__file__).resolve().parents[1]
RNG = np.random.default_rng(15)
IDENTITY = "0 0 0 0 0 0 1"


def write_ply(path: Path, points: np.ndarray) -> Path:
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n").encode()
    path.write_bytes(header + np.asarray(points, "<f4").tobytes())
    return path


def relief(n: int) -> np.ndarray:
    u, v = RNG.random(n), RNG.random(n)
    return np.column_stack([u * 100, v * 100, 5 * np.sin(4 * u) * np.cos(3 * v)])


def write_conf(path: Path, names: list[str]) -> Path:
    path.write_text("".join(f"bmesh {name} {IDENTITY}\n" for name in names))
    return path


def gzip_bomb(path: Path, row: bytes, nbytes: int) -> Path:
    """A gzip file of ``row`` repeated to ``nbytes`` decompressed bytes: one compressed
    MiB written as many gzip members (valid gzip; its trailer states the last member's
    size only, so only the streamed count sees the whole)."""
    block = row * ((16 << 20) // len(row))
    member = gzip.compress(block, compresslevel=9)
    with open(path, "wb") as out:
        for _ in range(nbytes // len(block)):
            out.write(member)
    return path


# ------------------------------------------------------------------------ .conf paths
@pytest.mark.parametrize("listed,match", [
    ("/etc/passwd", "absolute path"),
    ("../outside.ply", "leads out of its folder"),
    ("sub/../../outside.ply", "leads out of its folder"),
    ("C:/scan.ply", "absolute path"),
])
def test_conf_names_outside_its_folder_are_refused(tmp_path, listed, match):
    write_ply(tmp_path / "outside.ply", relief(100))
    folder = tmp_path / "registration"
    (folder / "sub").mkdir(parents=True)
    with pytest.raises(ScanError, match=match):
        load_scan(write_conf(folder / "r.conf", [listed]))


def test_conf_link_leading_out_is_refused(tmp_path):
    write_ply(tmp_path / "outside.ply", relief(100))
    folder = tmp_path / "registration"
    folder.mkdir()
    (folder / "inside.ply").symlink_to(tmp_path / "outside.ply")
    with pytest.raises(ScanError, match="a link to .*outside its folder"):
        load_scan(write_conf(folder / "r.conf", ["inside.ply"]))


def test_conf_link_inside_its_folder_is_read(tmp_path):
    write_ply(tmp_path / "a.ply", relief(100))
    (tmp_path / "b.ply").symlink_to(tmp_path / "a.ply")
    assert load_scan(write_conf(tmp_path / "r.conf", ["b.ply"])).n_points == 100


def test_conf_naming_one_file_many_times_is_refused(tmp_path):
    write_ply(tmp_path / "s.ply", relief(3000))
    conf = write_conf(tmp_path / "r.conf", ["s.ply"] * 2000)  # the 3 GB .conf
    with pytest.raises(ScanError, match=r"names 2,000 scan files, over the limit max_files"):
        load_scan(conf)
    with pytest.raises(ScanError, match="names s.ply more than once"):
        load_scan(conf, limits=InputLimits(max_files=5000))
    (tmp_path / "t.ply").symlink_to(tmp_path / "s.ply")  # the same file by another name
    with pytest.raises(ScanError, match="names s.ply more than once"):
        load_scan(write_conf(tmp_path / "r2.conf", ["s.ply", "t.ply"]))


def test_conf_with_too_many_files_is_refused(tmp_path):
    names = [write_ply(tmp_path / f"s{k}.ply", relief(50)).name for k in range(4)]
    conf = write_conf(tmp_path / "r.conf", names)
    with pytest.raises(ScanError, match=r"names 4 scan files, over the limit max_files = 3"
                       r".*--max-files"):
        load_scan(conf, limits=InputLimits(max_files=3))
    assert load_scan(conf, limits=InputLimits(max_files=4)).n_points == 200


def test_conf_points_count_together(tmp_path):
    names = [write_ply(tmp_path / f"s{k}.ply", relief(400)).name for k in range(3)]
    conf = write_conf(tmp_path / "r.conf", names)
    with pytest.raises(ScanError, match=r"s2.ply: 400 more points make 1,200 in all, over "
                       r"the limit max_points = 1,000.*--max-points"):
        load_scan(conf, limits=InputLimits(max_points=1000))
    assert load_scan(conf, limits=InputLimits(max_points=1200)).n_points == 1200


def test_conf_listed_gzip_bomb_is_refused(tmp_path):
    gzip_bomb(tmp_path / "bomb.xyz.gz", b"0 0 0\n", 64 << 20)
    conf = write_conf(tmp_path / "r.conf", ["bomb.xyz"])  # found as bomb.xyz.gz
    with pytest.raises(ScanError, match=r"bomb.xyz.gz: the gzip stream expands .*"
                       r"decompression bomb, over the limit max_ratio = 200"):
        load_scan(conf)


# ------------------------------------------------------------------------ gzip streams
def test_gzip_bomb_refused_by_its_trailer_or_within_one_chunk(tmp_path):
    one = tmp_path / "one.xyz.gz"  # a single member: its trailer states the whole size
    one.write_bytes(gzip.compress(b"0 0 0\n" * (10 << 20)))
    with pytest.raises(ScanError, match=r"one.xyz.gz: the gzip stream declares 60.0 MiB .*"
                       r"over the limit max_ratio = 200"):
        load_scan(one)
    path = gzip_bomb(tmp_path / "bomb.xyz.gz", b"0 0 0\n", 64 << 20)
    data = bytearray(path.read_bytes())
    data[-4:] = (100).to_bytes(4, "little")  # the trailer lies: only the count can tell
    path.write_bytes(bytes(data))
    with pytest.raises(ScanError, match=r"expands to more than .* read so far \(ratio \d+\)"
                       r".*max_ratio = 200"):
        load_scan(path)


def test_gzip_total_expanded_bytes_limit(tmp_path):
    path = tmp_path / "c.xyz.gz"
    text = io.StringIO()
    np.savetxt(text, RNG.random((40_000, 3)), fmt="%.6f")
    path.write_bytes(gzip.compress(text.getvalue().encode()))
    with pytest.raises(ScanError, match=r"over the limit max_expanded_bytes = 100.0 KiB.*"
                       r"--max-expanded-bytes"):
        load_scan(path, limits=InputLimits(max_expanded_bytes=100 << 10))
    assert load_scan(path).n_points == 40_000


def test_text_rows_counted_as_they_are_parsed(tmp_path):
    path = tmp_path / "c.xyz"
    np.savetxt(path, RNG.random((5000, 3)))
    with pytest.raises(ScanError, match=r"c.xyz: .*over the limit max_points = 1,000"):
        load_scan(path, limits=InputLimits(max_points=1000))
    pts = tmp_path / "c.pts"
    pts.write_text("1000000000000\n1 2 3\n")
    with pytest.raises(ScanError, match=r"c.pts: 1,000,000,000,000 points, over the limit"):
        load_scan(pts)


def test_ply_vertex_count_checked_before_allocation(tmp_path):
    path = write_ply(tmp_path / "s.ply", relief(2000))
    with pytest.raises(ScanError, match=r"s.ply: 2,000 points, over the limit max_points"):
        load_scan(path, limits=InputLimits(max_points=1999))


@pytest.mark.parametrize("field,value,match", [
    ("max_points", 0, "max_points must be a number >= 1"),
    ("max_ratio", float("nan"), "max_ratio must be a number >= 1"),
    ("max_files", True, "max_files must be a number >= 1"),
    ("context", "web", "context must be one of cli, upload"),
])
def test_bad_limits(field, value, match):
    with pytest.raises(ValueError, match=match):
        InputLimits(**{field: value})


BOMB_SCRIPT = r"""
import json, resource, sys, time
from fitter.fitting.io import ScanError, load_scan
start = time.perf_counter()
try:
    load_scan(sys.argv[1])
    outcome = "accepted"
except ScanError as exc:
    outcome = str(exc)
# VmHWM is this program's own peak; ru_maxrss also counts the parent's RSS at fork (Linux)
try:
    peak = next(int(line.split()[1]) for line in open("/proc/self/status")
                if line.startswith("VmHWM:")) / 1024
except (OSError, StopIteration):
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"seconds": time.perf_counter() - start, "outcome": outcome,
                  "peak_mb": peak}))
"""


def refusal_cost(path: Path) -> dict:
    done = subprocess.run([sys.executable, "-c", BOMB_SCRIPT, str(path)], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_cli_amplification_inputs_refused_fast_and_small(tmp_path):
    """The issue's CLI inputs: an 874 KB .xyz.gz (7 GB before) and a .conf listing one
    PLY thousands of times (6 GB before): refused within 1 s, under 300 MB peak."""
    xyz = gzip_bomb(tmp_path / "bomb.xyz.gz", b"0 0 0\n", 600 << 20)
    assert xyz.stat().st_size < 1 << 20
    write_ply(tmp_path / "s.ply", relief(3000))
    conf = write_conf(tmp_path / "r.conf", ["s.ply"] * 50_000)
    for path, match in ((xyz, "decompression bomb"), (conf, "names 50,000 scan files")):
        cost = refusal_cost(path)
        assert match in cost["outcome"]
        assert cost["seconds"] < 3.0 and cost["peak_mb"] < 300, cost  # 2 shared cores: slack


# ------------------------------------------------------------------------ uploads
def upload_zip(tmp_path: Path, members: dict[str, bytes],
               compression: int = zipfile.ZIP_DEFLATED) -> ReceivedFile:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    folder = tmp_path / "upload"
    folder.mkdir()
    path = folder / "received"
    path.write_bytes(buffer.getvalue())
    return ReceivedFile(path, "scan.zip", path.stat().st_size, "0" * 64)


def ply_bytes(points: np.ndarray, tmp_path: Path) -> bytes:
    return write_ply(tmp_path / "tmp.ply", points).read_bytes()


@pytest.mark.parametrize("conf,match", [
    ("bmesh /etc/passwd " + IDENTITY, "absolute path"),
    ("bmesh ../../../etc/passwd " + IDENTITY, "leads out of its folder"),
    (("bmesh s.ply " + IDENTITY + "\n") * 3, "more than once"),
    ("bmesh missing.ply " + IDENTITY, "neither"),
])
def test_upload_conf_checked_before_the_fit(tmp_path, conf, match):
    received = upload_zip(tmp_path, {"r.conf": conf.encode(),
                                     "s.ply": ply_bytes(relief(100), tmp_path)})
    with pytest.raises(UploadError, match=match):
        prepare_scan(received, UploadLimits())


def test_upload_conf_listing_a_gzip_bomb_is_refused(tmp_path):
    bomb = gzip_bomb(tmp_path / "b.gz", b"0 0 0\n", 32 << 20).read_bytes()
    received = upload_zip(tmp_path, {"r.conf": f"bmesh b.xyz {IDENTITY}\n".encode(),
                                     "b.xyz.gz": bomb}, zipfile.ZIP_STORED)  # zip ratio 1
    with pytest.raises(UploadError, match=r"decompression bomb.*TESSERA_UPLOAD_MAX_RATIO") as exc:
        prepare_scan(received, UploadLimits())
    assert exc.value.status == 400


def test_upload_conf_file_count_uses_the_upload_setting(tmp_path):
    members = {f"s{k}.ply": ply_bytes(relief(50), tmp_path) for k in range(3)}
    members["r.conf"] = "".join(f"bmesh s{k}.ply {IDENTITY}\n" for k in range(3)).encode()
    with pytest.raises(UploadError, match=r"^r.conf: names 3 scan files.*TESSERA_UPLOAD_MAX_FILES"):
        prepare_scan(upload_zip(tmp_path, members), UploadLimits(max_files=2))


def test_upload_limits_are_the_input_limits():
    limits = UploadLimits()
    assert isinstance(limits, InputLimits) and limits.context == "upload"
    assert limits.max_bytes == 4 << 30 and limits.max_expanded_bytes == 16 << 30
    from fitter.server import DEFAULTS  # the settings' defaults are the limits' defaults
    for setting, field in (("TESSERA_UPLOAD_MAX_POINTS", "max_points"),
                           ("TESSERA_UPLOAD_MAX_FILES", "max_files"),
                           ("TESSERA_UPLOAD_MAX_RATIO", "max_ratio"),
                           ("TESSERA_UPLOAD_MAX_EXPANDED_BYTES", "max_expanded_bytes"),
                           ("TESSERA_UPLOAD_MAX_BYTES", "max_bytes")):
        assert DEFAULTS[setting][0] == getattr(limits, field)


# ------------------------------------------------------------------------ the CLI
def test_cli_input_limit_flags(tmp_path, capsys):
    scan = write_ply(tmp_path / "s.ply", relief(2000))
    from fitter.cli import main

    assert main(["fit", str(scan), "-o", str(tmp_path / "b"), "-q", "--max-points", "1000"]) == 2
    assert "s.ply: 2,000 points, over the limit max_points = 1,000" in capsys.readouterr().err
    assert main(["fit", str(scan), "-o", str(tmp_path / "b"), "-q", "--grid", "12",
                 "--memory-budget", "1M"]) == 2
    assert "over the memory budget of 0.00 GiB" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["fit", str(scan), "-o", str(tmp_path / "b"), "--max-expanded-bytes", "lots"])
    assert "expected a number of bytes" in capsys.readouterr().err


# ------------------------------------------------------------------------ memory budget
def test_memory_estimates_grow_as_documented():
    assert base_fit_bytes((1024, 1024), 2, 60_000) > 16 << 30  # the 6 GB form input
    assert base_fit_bytes((128, 128), 2, 60_000) < 256 << 20
    assert detail_level_bytes(7, 64, 2) > 400 << 30  # levels 8, spans 64
    assert detail_level_bytes(5, 16, 2) < DEFAULT_MEMORY_BUDGET  # the automatic maximum


def test_detail_levels_over_the_budget_are_refused_before_any_solve(tmp_path):
    options = FitOptions(grid=(12, 12), detail_levels=8, detail_spans=64, texture=False)
    with pytest.raises(OptionError, match=r"detail_levels 8 with detail_spans 64: level 7 "
                       r"solves for 8,194\^2 coefficients, about .* GiB, over the memory "
                       r"budget of 2.00 GiB; at most 4 levels fit"):
        fit_scan(relief(40_000), tmp_path / "b", options)
    assert not (tmp_path / "b").exists()


def test_grid_over_the_budget_is_refused(tmp_path):
    with pytest.raises(OptionError, match=r"grid 512x512 .* over the memory budget of "
                       r"2.00 GiB; a grid of at most \d+x\d+ fits"):
        fit_scan(relief(5000), tmp_path / "b", FitOptions(grid=(512, 512)))
    # the form's 1024x1024 holds more control points than a patch may (client_py.format)
    with pytest.raises(OptionError, match=r"grid 1024x1024 has 1048576 control points; a "
                       r"patch holds at most 262144"):
        fit_scan(relief(5000), tmp_path / "b", FitOptions(grid=(1024, 1024)))
    with pytest.raises(OptionError, match=r"grid 200x200 .*max_grid"):
        fit_scan(relief(5000), tmp_path / "b",
                 FitOptions(grid=(12, 12), max_error=1e-9, max_grid=200),
                 memory_budget=64 << 20)


def test_automatic_depth_is_capped_and_recorded():
    plan = plan_memory((40, 40), 2, 60_000, None, 5, 64, 2)
    assert plan.detail_levels == 4 and plan.detail_levels_uncapped == 5
    assert plan.detail_bytes <= DEFAULT_MEMORY_BUDGET
    assert plan_memory((40, 40), 2, 60_000, None, 5, 16, 2).detail_levels_uncapped is None
    with pytest.raises(ValueError, match="memory_budget must be a positive number of bytes"):
        plan_memory((40, 40), 2, 60_000, None, 5, 16, 2, budget=0)


def test_capped_plan_in_the_manifest(tmp_path):
    options = FitOptions(grid=(12, 12), detail_spans=4, texture=False)
    bundle = fit_scan(relief(20_000), tmp_path / "b", options,
                      memory_budget=16 << 20)  # level 3 (34^2) fits, level 4 (66^2) not
    memory = bundle.manifest["memory"]
    assert memory["detail_levels"] == 4 and memory["detail_levels_uncapped"] == 5
    assert len(bundle.manifest["tiles"]["detail"]["levels"]) == 4


# ------------------------------------------------------------------------ degenerate scans
def collinear(n: int) -> np.ndarray:
    t = RNG.random(n)
    return np.column_stack([t, 2 * t + 1, -t])


@pytest.mark.parametrize("points,projection,match", [
    (collinear(1000), "auto", "degenerate scan: the points are collinear"),
    (RNG.integers(0, 2, (1000, 1)) * np.ones((1, 3)), "auto", "only 2 distinct"),
    (np.repeat(relief(8), 125, axis=0), "auto", "1,000 points but only 8 distinct"),
    (np.column_stack([relief(1000)[:, :2], np.zeros(1000)]), "cylinder",
     "projection=cylinder: the points lie in a plane"),
    (np.column_stack([relief(1000)[:, :2], np.zeros(1000)]), "sphere",
     "projection=sphere: the points lie in a plane"),
])
def test_degenerate_scans_are_refused(tmp_path, points, projection, match):
    with pytest.raises(ScanError, match=match):
        fit_scan(points, tmp_path / "b", FitOptions(grid=(8, 8), projection=projection))
    assert not (tmp_path / "b").exists()


def test_a_flat_cloud_still_fits_with_the_plane_map(tmp_path):
    flat = np.column_stack([relief(2000)[:, :2], np.zeros(2000)])
    bundle = fit_scan(flat, tmp_path / "b", FitOptions(grid=(8, 8), detail_levels=0))
    assert bundle.manifest["projection"]["kind"] == "plane"


def test_degenerate_patch_is_refused_before_writing():
    from fitter.fitting.degenerate import check_patch
    from fitter.fitting.nurbs import PatchModel

    model = PatchModel.uniform((4, 4), (2, 2))
    flat = model.copy()
    flat.Q[:] = 1.0  # every control point the same: a patch of zero area
    with pytest.raises(ScanError, match="degenerate patch: its area is 0"):
        check_patch(flat, "s.ply", 10.0)
    broken = model.copy()
    broken.Q[1, 2, 0] = np.nan
    with pytest.raises(ScanError, match="degenerate patch: 1 of 16 control points are not"):
        check_patch(broken, "s.ply", 10.0)
    negative = model.copy()
    negative.W[0, 0] = -1.0
    with pytest.raises(ScanError, match="weights must be > 0"):
        check_patch(negative, "s.ply", 10.0)

