"""``tessera tessellate`` through fitter.cli.main: .tsp files and bundle directories in,
PLY in the scan's coordinates out; bad input exits with status 2 and a message."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from nurbs_cases import random_surface

from client_py import NurbsSurface, read_patch, write_patch
from fitter.cli import main

# patch frame -> scan frame: a rotation about z, a scale and a shift
TRANSFORM = [[0.0, -2.0, 0.0, 250.0], [2.0, 0.0, 0.0, -40.0], [0.0, 0.0, 2.0, 1200.0],
             [0.0, 0.0, 0.0, 1.0]]


@pytest.fixture
def patch_file(tmp_path):
    s = random_surface(np.random.default_rng(5), 2, 2, 6, 5)
    s = NurbsSurface(s.degree, s.knots, s.control_points, s.weights,
                     metadata={"units": "mm", "transform": TRANSFORM})
    path = tmp_path / "relief.tsp"
    path.write_bytes(write_patch(s))
    return path


def expected_vertices(path, resolution):
    """The decoded patch evaluated on the grid, then mapped by TRANSFORM with numpy."""
    s = read_patch(path.read_bytes())
    ts = np.linspace(0.0, 1.0, resolution)
    local = np.array([s.evaluate(u, v) for u in ts for v in ts])
    m = np.array(TRANSFORM)
    return local @ m[:3, :3].T + m[:3, 3]


def test_tessellate_a_patch_file(patch_file, tmp_path, capsys):
    out = tmp_path / "mesh.ply"
    assert main(["tessellate", str(patch_file), "-o", str(out), "--resolution", "17"]) == 0
    assert f"{out}: 289 vertices, 512 triangles" in capsys.readouterr().out
    data = out.read_bytes()
    assert data.startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert b"comment source relief.tsp\ncomment units mm\n" in data
    mesh = trimesh.load(out, process=False)
    assert mesh.vertices.shape == (289, 3) and mesh.faces.shape == (512, 3)
    ref = expected_vertices(patch_file, 17)
    assert np.abs(mesh.vertices - ref).max() <= 1e-6 * np.abs(ref).max()  # float32


def test_tessellate_a_bundle_directory_in_ascii(patch_file, tmp_path):
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "base.tsp").write_bytes(patch_file.read_bytes())
    out = tmp_path / "mesh.ply"
    assert main(["tessellate", str(bundle), "-o", str(out), "--resolution", "5", "--ascii"]) == 0
    assert out.read_bytes().startswith(b"ply\nformat ascii 1.0\n")
    mesh = trimesh.load(out, process=False)
    assert mesh.vertices.shape == (25, 3) and mesh.faces.shape == (32, 3)
    ref = expected_vertices(patch_file, 5)
    assert np.abs(mesh.vertices - ref).max() <= 1e-6 * np.abs(ref).max()


@pytest.mark.parametrize(
    ("make_input", "message"),
    [
        (lambda d: d / "missing.tsp", "missing.tsp: no such patch file"),
        (lambda d: d, "base.tsp: no such patch file (give a .tsp file or a bundle directory)"),
        (lambda d: (d / "x.tsp").write_bytes(b"TSPF\x01") and d / "x.tsp",
         "x.tsp: invalid Tessera patch at byte 5: truncated"),
        (lambda d: (d / "y.tsp").write_bytes(b"solid ascii stl\n") and d / "y.tsp",
         "y.tsp: invalid Tessera patch at byte 0: magic is b'soli'"),
    ],
)
def test_bad_input_exits_2_with_a_message(tmp_path, capsys, make_input, message):
    path = make_input(tmp_path)
    status = main(["tessellate", str(path), "-o", str(tmp_path / "out.ply")])
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith("tessera tessellate: error: ") and message in err
    assert "Traceback" not in err
    assert not (tmp_path / "out.ply").exists()


def test_corrupted_patch_exits_2(patch_file, tmp_path, capsys):
    data = bytearray(patch_file.read_bytes())
    data[30] ^= 0xFF
    patch_file.write_bytes(bytes(data))
    assert main(["tessellate", str(patch_file), "-o", str(tmp_path / "o.ply")]) == 2
    assert "CRC32 mismatch" in capsys.readouterr().err


def test_unwritable_output_exits_2(patch_file, tmp_path, capsys):
    out = tmp_path / "no" / "such" / "dir" / "mesh.ply"
    assert main(["tessellate", str(patch_file), "-o", str(out), "--resolution", "3"]) == 2
    assert "tessera tessellate: error:" in capsys.readouterr().err


@pytest.mark.parametrize("resolution", ["1", "abc"])
def test_bad_resolution_is_a_usage_error(patch_file, tmp_path, capsys, resolution):
    with pytest.raises(SystemExit) as info:
        main(["tessellate", str(patch_file), "-o", str(tmp_path / "o.ply"),
              "--resolution", resolution])
    assert info.value.code == 2
    assert "--resolution" in capsys.readouterr().err


def test_help_explains_every_option(capsys):
    with pytest.raises(SystemExit) as info:
        main(["tessellate", "--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    for option in ("--output", "--resolution", "--ascii", "bundle directory", "base.tsp"):
        assert option in text


@pytest.fixture
def level_bundle(patch_file, tmp_path):
    """A bundle directory: the patch and one level-0 detail tile of 3 spans (grid 7 x 7)."""
    from client_py import DetailTile, write_detail_tile

    bundle = tmp_path / "tiny"
    (bundle / "detail" / "0").mkdir(parents=True)
    (bundle / "base.tsp").write_bytes(patch_file.read_bytes())
    values = tuple((7 * k) % 11 - 5 for k in range(25))
    data = write_detail_tile(DetailTile(0, 0, 0, 2, 3, 2.0**-6, values))
    (bundle / "detail/0/0_0.tsd").write_bytes(data)
    manifest = {"tiles": {"detail": {"spans_per_tile": 3, "levels": [{"level": 0, "rms": 0.1}],
                                     "nodes": [{"level": 0, "i": 0, "j": 0, "bytes": len(data),
                                                "file": "detail/0/0_0.tsd"}]}}}
    (bundle / "manifest.json").write_text(json.dumps(manifest))
    return bundle


def test_a_bundle_level_takes_the_plan_grid_unless_told(level_bundle, tmp_path, capsys):
    out = tmp_path / "level.ply"
    assert main(["tessellate", str(level_bundle), "--level", "0", "-o", str(out)]) == 0
    assert f"{out}: level 0, 49 vertices" in capsys.readouterr().out  # 2 x 3 x 2^0 + 1 = 7
    header = out.read_bytes().split(b"end_header")[0]
    assert b"comment source tiny\ncomment units mm\n" in header
    assert b"comment detail level 0: base patch + 1 detail tiles of levels 0..0\n" in header
    assert main(["tessellate", str(level_bundle), "-o", str(out), "--resolution", "5"]) == 0
    assert f"{out}: level 0, 25 vertices" in capsys.readouterr().out
    # the base alone: the default grid of a patch
    assert main(["tessellate", str(level_bundle), "--level", "-1", "-o", str(out)]) == 0
    assert f"{out}: level -1, {256 * 256} vertices" in capsys.readouterr().out


def test_a_bundle_tile_that_is_missing_exits_2(level_bundle, tmp_path, capsys):
    (level_bundle / "detail/0/0_0.tsd").unlink()
    assert main(["tessellate", str(level_bundle), "-o", str(tmp_path / "o.ply")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tessera tessellate: error: ") and "0_0.tsd" in err
    assert "Traceback" not in err
