"""A single patch's detached pieces (``fitter.fitting.pieces``, ``pieces.tsa``): fitted, listed
in the manifest, drawn by every client path, and bad input refused or left uncovered."""

from __future__ import annotations

import json
import shutil
import zlib

import numpy as np
import pytest
import trimesh
from fragment_scan import FRAGMENT, fragment_scan, grid_mesh

from client_py.atlas_format import read_atlas
from client_py.bundle import (
    PIECES_FILE,
    ManifestError,
    pieces_entry,
    plan_level,
    read_pieces,
    tessellate_bundle,
)
from client_py.mesh_arrays import mesh_arrays
from client_py.session import WorkerSession
from fitter.cli import main as tessera
from fitter.fitting.atlas.measure import point_mesh_distance
from fitter.fitting.io.scan import make_scan
from fitter.fitting.options import FitOptions
from fitter.fitting.pieces import (
    MAX_PIECES_SHARE,
    MIN_PIECE_POINTS,
    PIECE_REACH,
    far_pieces,
    fit_pieces,
)
from fitter.fitting.pipeline import fit_scan


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    """The relief fitted with its fragment and without, as one patch (``patches=1``: the
    pieces are a single patch's; with the smooth base, the default, a mesh is an atlas)."""
    root = tmp_path_factory.mktemp("pieces")
    for fragment in (True, False):
        fit_scan(fragment_scan(fragment), root / f"fragment-{fragment}", FitOptions(patches=1))
    return root


def _read(bundle):
    return lambda name: (bundle / name).read_bytes()


def test_the_fragment_is_a_piece_drawn_with_the_patch_and_not_without(bundles):
    bundle = bundles / "fragment-True"
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["format_version"] == 1 and manifest["base"]["file"] == "base.tsp"
    entry = manifest["pieces"]
    assert entry["file"] == PIECES_FILE and entry["pieces"] == 1 and entry["points"] == FRAGMENT
    assert entry["uncovered"] == [] and entry["reach"] == PIECE_REACH
    assert manifest["files"][PIECES_FILE] == (bundle / PIECES_FILE).stat().st_size > 0
    pieces, _ = read_atlas((bundle / PIECES_FILE).read_bytes())
    assert len(pieces.quads) == entry["patches"]
    scan = fragment_scan(True)
    fragment = scan.points[-FRAGMENT:]
    diagonal = float(np.linalg.norm(np.ptp(scan.points, axis=0)))
    without = {k: v for k, v in manifest.items() if k != "pieces"}  # what an older reader draws
    before = point_mesh_distance(fragment, *mesh_arrays(tessellate_bundle(without, _read(bundle))))
    after = point_mesh_distance(fragment, *mesh_arrays(tessellate_bundle(manifest, _read(bundle))))
    assert before.min() > 0.1 * diagonal  # the height field does not reach it
    assert after.max() < 0.002 * diagonal  # the piece does
    drawn, patch = (tessellate_bundle(m, _read(bundle)) for m in (manifest, without))
    n, m = len(patch.positions), len(patch.indices)  # the patch as before, the pieces after it
    assert drawn.positions[:n] == patch.positions and drawn.indices[:m] == patch.indices
    assert min(drawn.indices[m:]) == len(patch.positions) // 3


def _quality(path) -> np.ndarray:
    """``error.ply``'s per-point ``quality`` (the signed deviation written)."""
    return np.asarray(trimesh.load(path, process=False).metadata["_ply_raw"]["vertex"]
                      ["data"]["quality"], dtype=float)


def test_the_figures_are_of_the_patch_with_its_pieces(bundles):
    """With pieces the manifest's figures, ``error.ply`` and the raster are of what is drawn:
    the fragment's points measured against the pieces (near), not the patch (0.4 away), and
    counted as represented; the patch's own points as without pieces."""
    bundle = bundles / "fragment-True"
    manifest = json.loads((bundle / "manifest.json").read_text())
    scan = fragment_scan(True)
    n, diagonal = scan.n_points, float(np.linalg.norm(np.ptp(scan.points, axis=0)))
    d = _quality(bundle / "error.ply")  # float32, as written
    drawn = tessellate_bundle(manifest, _read(bundle), level=-1)  # patch + pieces, base level
    reference = point_mesh_distance(scan.points, *mesh_arrays(drawn))
    assert np.abs(np.abs(d) - reference).max() < 0.002 * diagonal  # foot point vs. triangles
    assert np.abs(d[-FRAGMENT:]).max() < 0.002 * diagonal  # the pieces draw the fragment
    every = manifest["stats_all_points"]
    assert every["points"] == n and every["max"] < 0.01 * diagonal
    assert np.isclose(every["rms"], np.sqrt(np.mean(d**2)), rtol=1e-5)
    stats, projection = manifest["stats"], manifest["projection"]
    assert projection["uncovered_points"] == n - stats["points"] < FRAGMENT  # drawn: covered
    raster = manifest["error_raster"]
    assert stats["max"] <= every["max"] and raster["max"] == stats["max"]
    # the raster is of the points patch and pieces represent: the worst one's cell is its max
    codes = np.frombuffer(zlib.decompress((bundle / raster["file"]).read_bytes()), np.uint8)
    assert codes[codes < 255].max() == 254
    assert projection["uncovered_bbox"] is None or (
        np.asarray(projection["uncovered_bbox"])[:, 2] > -0.3).all()  # not the fragment


def test_the_thumbnail_draws_the_pieces(bundles):
    """The gallery's card holds the pieces as the viewer draws them: from the front the
    fragment is hidden behind the relief (the same card), from behind it is in front."""
    import io

    from PIL import Image

    from fitter.collection.bundles import Collection
    from fitter.server.thumbnail import pieces_of, render_thumbnail, thumbnail_of

    bundle = Collection(bundles).get("fragment-True")
    pieces = pieces_of(bundle)
    assert pieces is not None and len(pieces.positions) // 3 > 0
    patch = (bundle.path / "base.tsp").read_bytes()
    front = {"up": [0, 1, 0], "front": [0, 0, 1]}
    back = {"up": [0, 1, 0], "front": [0, 0, -1]}
    assert render_thumbnail(patch, front, pieces) == render_thumbnail(patch, front)
    assert thumbnail_of(bundle).png == render_thumbnail(patch, bundle.manifest["view"], pieces)

    def card(png):
        return np.asarray(Image.open(io.BytesIO(png))).astype(float)

    seen, alone = card(render_thumbnail(patch, back, pieces)), card(render_thumbnail(patch, back))
    changed = np.argwhere(np.abs(seen - alone).max(axis=2) > 8)
    assert len(changed) > 20
    # seen from behind, x is mirrored: the fragment (x in 0.2..0.35 of -1..1) is left of centre
    assert (changed[:, 1] < 160).all() and (changed[:, 1] > 100).all()
    assert pieces_of(Collection(bundles).get("fragment-False")) is None


def test_no_piece_no_entry_and_no_file(bundles):
    bundle = bundles / "fragment-False"
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert "pieces" not in manifest and not (bundle / PIECES_FILE).exists()
    assert PIECES_FILE not in manifest["files"] and pieces_entry(manifest) is None


def test_cli_and_worker_plys_hold_the_pieces(bundles, tmp_path):
    bundle = bundles / "fragment-True"
    manifest = json.loads((bundle / "manifest.json").read_text())
    level = plan_level(manifest).level
    drawn = tessellate_bundle(manifest, _read(bundle))
    assert tessera(["tessellate", str(bundle), "-o", str(tmp_path / "m.ply")]) == 0
    cli = trimesh.load(tmp_path / "m.ply", process=False)
    assert len(cli.faces) == drawn.triangle_count
    np.testing.assert_allclose(cli.vertices, mesh_arrays(drawn)[0], atol=1e-6)
    session = WorkerSession(kernel="numpy")
    session.load_patch((bundle / "base.tsp").read_bytes(), "base.tsp")
    session.read_manifest((bundle / "manifest.json").read_text())
    pieces = session.load_pieces((bundle / PIECES_FILE).read_bytes())
    plan = plan_level(manifest, level)
    ply = session.level_ply(level, {name: (bundle / name).read_bytes()
                                    for name in plan.detail_files})
    assert ply.triangle_count == drawn.triangle_count
    base = session.base_ply(32)
    assert base.triangle_count == 2 * 31 * 31 + pieces.triangle_count


def _manifest_with(bundle, **pieces) -> dict:
    manifest = json.loads((bundle / "manifest.json").read_text())
    manifest["pieces"] = {**manifest["pieces"], **pieces}
    return manifest


@pytest.mark.parametrize(("change", "where"), [
    ({"file": "../pieces.tsa"}, "pieces.file"),
    ({"file": "base.tsp"}, "pieces.file"),
    ({"patches": 0}, "pieces.patches"),
    ({"patches": "9"}, "pieces.patches"),
    ({"resolution": 1}, "pieces.resolution"),
    ({"resolution": 4097}, "pieces.resolution"),
])
def test_a_bad_pieces_entry_is_refused_by_name(bundles, change, where):
    manifest = _manifest_with(bundles / "fragment-True", **change)
    with pytest.raises(ManifestError) as caught:
        tessellate_bundle(manifest, _read(bundles / "fragment-True"))
    assert caught.value.where == where


def test_pieces_that_are_not_the_manifests_are_refused(bundles, tmp_path):
    bundle = bundles / "fragment-True"
    manifest = json.loads((bundle / "manifest.json").read_text())
    wrong = _manifest_with(bundle, patches=manifest["pieces"]["patches"] + 1)
    with pytest.raises(ManifestError, match="pieces.patches"):
        read_pieces(wrong, _read(bundle))
    copy = tmp_path / "copy"
    shutil.copytree(bundle, copy)
    (copy / PIECES_FILE).write_bytes(b"TSA" + bytes(40))
    with pytest.raises(Exception) as caught:  # the format's own error, not a crash elsewhere
        tessellate_bundle(manifest, _read(copy))
    assert type(caught.value).__name__ == "PatchFormatError"
    assert str(caught.value).endswith(f"({PIECES_FILE})")  # the file named
    atlas_manifest = {**manifest, "format_version": 2}
    with pytest.raises(ManifestError, match="version-1"):
        pieces_entry(atlas_manifest)
    session = WorkerSession(kernel="numpy")
    session.load_patch((bundles / "fragment-False" / "base.tsp").read_bytes(), "base.tsp")
    session.read_manifest((bundles / "fragment-False" / "manifest.json").read_text())
    with pytest.raises(ValueError, match="no pieces"):
        session.load_pieces((bundle / PIECES_FILE).read_bytes())


def test_an_entry_without_a_file_draws_the_patch_alone(bundles):
    bundle = bundles / "fragment-True"
    manifest = _manifest_with(bundle, file=None)
    without = {k: v for k, v in manifest.items() if k != "pieces"}
    assert tessellate_bundle(manifest, _read(bundle)).triangle_count == \
        tessellate_bundle(without, _read(bundle)).triangle_count


def test_far_pieces_joins_far_points_by_far_triangles():
    faces = np.array([[0, 1, 2], [1, 2, 3], [4, 5, 6], [6, 7, 8], [2, 4, 9]])
    far = np.zeros(11, dtype=bool)
    far[[0, 1, 2, 3, 5, 6, 7, 8, 10]] = True  # 4 and 9 near: [2, 4, 9] and [4, 5, 6] not far
    pieces, loose = far_pieces(faces, far)
    assert [p.tolist() for p in pieces] == [[0, 1, 2, 3], [6, 7, 8]]
    assert loose == 2  # points 5 and 10: on no far triangle


def test_a_piece_that_cannot_be_fitted_is_left_uncovered_with_the_reason(tmp_path):
    """Every far piece's triangles are degenerate (its points on one line): the atlas fit
    refuses it, the entry says why, no file is written, nothing raises."""
    points, faces = grid_mesh(30, (-1, 1), (-1, 1), lambda x, y: 0 * x)
    line = np.column_stack([np.linspace(0, 0.3, MIN_PIECE_POINTS + 5), np.zeros(25),
                            np.full(25, -0.5)])
    run = np.arange(len(points), len(points) + 23)
    flat = np.column_stack([run, run + 1, run + 2])
    scan = make_scan("line", np.concatenate([points, line]),
                     faces=np.concatenate([faces, flat]), source={"name": "line.ply"})
    far = np.r_[np.zeros(len(points)), np.ones(len(line))]
    entry = fit_pieces(scan, tmp_path, {}, distances=lambda folder, manifest, p: far)
    assert entry["file"] is None and entry["pieces"] == 0 and entry["points"] == 0
    [left] = entry["uncovered"]
    assert left["pieces"] == 1 and left["points"] == len(line)
    assert left["reason"].startswith("not fitted: ")
    assert not (tmp_path / PIECES_FILE).exists()


def test_small_pieces_and_clouds_give_no_entry(tmp_path):
    points, faces = grid_mesh(30, (-1, 1), (-1, 1), lambda x, y: 0 * x)
    scan = make_scan("grid", points, faces=faces, source={"name": "grid.ply"})
    small = np.zeros(len(points))
    small[:3] = 1.0  # three far corner points: fewer than MIN_PIECE_POINTS
    assert fit_pieces(scan, tmp_path, {}, distances=lambda *_: small) is None
    cloud = make_scan("cloud", points, source={"name": "cloud.xyz"})
    assert fit_pieces(cloud, tmp_path, {}, distances=lambda *_: np.ones(len(points))) is None
    assert not (tmp_path / PIECES_FILE).exists()


def test_pieces_over_the_share_are_left_to_an_atlas(tmp_path):
    """Far pieces holding over MAX_PIECES_SHARE of the points: no fit, the reason names the
    share (a scan that is no height field with a few fragments)."""
    points, faces = grid_mesh(30, (-1, 1), (-1, 1), lambda x, y: 0 * x)
    scan = make_scan("grid", points, faces=faces, source={"name": "grid.ply"})
    far = np.zeros(len(points))
    far[:10 * 30] = 1.0  # ten rows of the grid: one piece of a third of the points
    entry = fit_pieces(scan, tmp_path, {}, distances=lambda *_: far)
    assert entry["file"] is None and entry["pieces"] == 0
    assert entry["uncovered"] == [{"pieces": 1, "points": 300, "reason": (
        f"not fitted: 33.3 % of the scan's points, over {100 * MAX_PIECES_SHARE:g} %: an "
        "atlas draws them (--patches auto or N)")}]
    assert not (tmp_path / PIECES_FILE).exists()
