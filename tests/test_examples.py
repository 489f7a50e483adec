"""The generated examples of ``make demo``: the vase is a closed mesh a scanner's
reconstruction could give, and it reads back through the fit's own reader."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fitter.demo import write_mesh_ply
from fitter.fitting.examples import VASE_HEIGHT, vase_mesh
from fitter.fitting.io import load_scan


def test_the_vase_is_one_closed_consistently_oriented_surface_of_genus_0():
    vertices, faces = vase_mesh()
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    assert mesh.euler_number == 2 and len(mesh.split(only_watertight=False)) == 1
    assert np.allclose(mesh.bounds[:, 2], [0.0, VASE_HEIGHT])
    # the belly with its flutes, wider than the foot and the neck
    assert 108.0 < mesh.bounds[1, 0] < 115.0


def test_the_vase_carries_its_bosses_and_flutes():
    around, rings = 256, 160
    vertices, _ = vase_mesh(around, rings)
    r = np.hypot(vertices[:-2, 0], vertices[:-2, 1]).reshape(rings, around)
    boss_ring = int(round(0.66 * (rings - 1)))
    assert r[boss_ring].max() - r[boss_ring].min() > 6.0  # 7 mm bosses, eight around
    belly = int(round(0.40 * (rings - 1)))
    spectrum = np.abs(np.fft.rfft(r[belly]))
    assert np.argmax(spectrum[1:]) + 1 == 20  # 20 flutes


def test_the_demos_vase_ply_reads_back_as_the_mesh(tmp_path):
    vertices, faces = vase_mesh(32, 12)
    path = tmp_path / "vase.ply"
    write_mesh_ply(path, vertices, faces)
    scan = load_scan(path)
    assert np.allclose(scan.points, vertices, atol=1e-4)
    assert scan.faces is not None and np.array_equal(scan.faces, faces)


@pytest.mark.parametrize("around, rings", [(4, 40), (64, 2)])
def test_a_vase_too_coarse_is_refused(around, rings):
    with pytest.raises(ValueError, match="at least 8 vertices around and 4 rings"):
        vase_mesh(around, rings)
