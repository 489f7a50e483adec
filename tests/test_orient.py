"""The object's up and front (fitter.fitting.orient): each rule on a scan built to need it,
the fit option and the manifest's ``view``, and the real scans against the up found by
looking at renders of them (../shared/data)."""

from __future__ import annotations

import numpy as np
import pytest

from fitter.fitting import orient
from fitter.fitting.io import load_scan
from fitter.fitting.io.scan import Scan
from fitter.fitting.options import OPTION, UP_AXES, FitOptions, OptionError, parse_form
from fitter.fitting.pipeline import fit_scan


def angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b),
                                              -1, 1))))


def cone_on_base(axis: int, sign: float, n: int = 20_000) -> Scan:
    """A cone standing on a flat disk: base (radius 1) at ``sign * -1.5`` along ``axis``,
    apex at ``sign * 1.5``; points on the side and on the base."""
    rng = np.random.default_rng(3)
    t = rng.uniform(0, 1, n)
    theta = rng.uniform(0, 2 * np.pi, n)
    side = np.column_stack([-1.5 + 3 * t, (1 - t) * np.cos(theta), (1 - t) * np.sin(theta)])
    r = np.sqrt(rng.uniform(0, 1, n // 2))
    phi = rng.uniform(0, 2 * np.pi, n // 2)
    base = np.column_stack([np.full(n // 2, -1.5), r * np.cos(phi), r * np.sin(phi)])
    local = np.vstack([side, base]) * [sign, 1, 1]
    points = np.roll(local, axis, axis=1)  # column 0 (the cone's axis) goes to ``axis``
    return Scan.from_array(points)


def test_the_option_table_offers_every_axis():
    assert UP_AXES == ("auto", *orient.AXES)
    assert OPTION["up"].cli == "--up" and OPTION["up"].form == "up"
    assert parse_form({"up": "-z"})["up"] == "-z"
    with pytest.raises(OptionError, match="up must be one of auto"):
        FitOptions(up="up").validate()


@pytest.mark.parametrize(("axis", "sign", "up"), [(2, 1.0, "+z"), (0, -1.0, "-x"), (1, 1.0, "+y")])
def test_base_plane_points_up_away_from_the_flat_end(axis, sign, up):
    view = orient.find_view(cone_on_base(axis, sign))
    assert view.up_source == "base plane"
    assert view.up == orient.AXES[up]


def test_the_option_overrides_and_a_bad_value_is_refused():
    scan = cone_on_base(2, 1.0)
    view = orient.find_view(scan, "-x")
    assert (view.up, view.up_source) == ((-1.0, 0.0, 0.0), "option")
    assert abs(np.dot(view.front, view.up)) < 1e-9
    with pytest.raises(ValueError, match="up must be auto or one of"):
        orient.find_view(scan, "down")


def test_the_format_decides_for_gltf_and_a_conf_registration():
    points = np.random.default_rng(0).normal(size=(500, 3)) * [1, 0.2, 3]  # flat in y
    scan = Scan.from_array(points)
    scan.source["format"] = "gltf"
    view = orient.find_view(scan)
    assert (view.up, view.front, view.up_source, view.front_source) == (
        (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), "format", "format")
    scan.source["format"] = "conf"
    view = orient.find_view(scan)
    assert (view.up, view.up_source, view.front_source) == ((0.0, 1.0, 0.0), "format",
                                                            "convention")


def test_no_base_no_normals_falls_back_to_the_convention():
    rng = np.random.default_rng(1)
    sphere = rng.normal(size=(5000, 3))
    view = orient.find_view(Scan.from_array(sphere / np.linalg.norm(sphere, axis=1,
                                                                   keepdims=True)))
    assert (view.up, view.front) == ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    assert (view.up_source, view.front_source) == ("convention", "convention")


def test_front_faces_the_detailed_side():
    """A closed box whose +x face is finely corrugated: the front is +x, perpendicular to up."""
    import trimesh

    box = trimesh.creation.box(extents=(1.0, 1.0, 3.0)).subdivide_to_size(0.05)
    vertices = box.vertices.copy()
    front_face = vertices[:, 0] > 0.49
    vertices[front_face, 0] += 0.02 * np.sin(vertices[front_face, 1] * 60) * np.sin(
        vertices[front_face, 2] * 60)
    scan = Scan.from_array(vertices)
    scan.faces = np.asarray(box.faces, dtype=np.int64)
    view = orient.find_view(scan, "+z")
    assert view.front_source == "surface detail"
    assert angle_deg(view.front, (1, 0, 0)) < 10


def test_the_manifest_records_the_view(tmp_path):
    # one patch: the view is found before the branch (pipeline.object_fields) and both
    # branches write it; auto lays this cone out as an atlas of 576 patches: 32 s of CPU
    # (its normal orientation now takes a second, not 70 s; the base fit's layout trials
    # take the most), too long to fit it twice here
    bundle = fit_scan(cone_on_base(2, 1.0).points, tmp_path / "cone",
                      FitOptions(grid=(8, 8), method="linear", detail_levels=0, patches=1))
    view = bundle.manifest["view"]
    assert view["up"] == [0.0, 0.0, 1.0] and view["up_source"] == "base plane"
    assert abs(np.dot(view["front"], view["up"])) < 1e-6
    forced = fit_scan(cone_on_base(2, 1.0).points, tmp_path / "forced",
                      FitOptions(grid=(8, 8), method="linear", detail_levels=0, up="-y",
                                 patches=1))
    assert forced.manifest["view"]["up"] == [0.0, -1.0, 0.0]
    assert forced.manifest["options"]["up"] == "-y"


#: the up of each real scan, established by rendering it from the six axis directions and
#: looking (heads up, bases down): Lucy stands along +z, every other scan along +y
REAL_UP = {
    "laurana-bust/laurana.ply": (0, 1, 0),
    "nefertiti/nefertiti-lowres.obj": (0, 1, 0),
    "stanford-lucy/lucy.ply": (0, 0, 1),
    "stanford-bunny/bun_zipper.ply.gz": (0, 1, 0),
    "stanford-bunny/bun000.ply.gz": (0, 1, 0),
    "happy-buddha-rangescans/happyStandRight.conf": (0, 1, 0),
    "bali-mask/mask.obj": (0, 1, 0),
    "bali-mask/mask-gltf-2.0_separated-valid.gltf": (0, 1, 0),
}


@pytest.mark.parametrize("name", sorted(REAL_UP))
def test_real_scans_stand_upright(shared_data, name):
    view = orient.find_view(load_scan(shared_data / name))
    assert angle_deg(view.up, REAL_UP[name]) < 15, view
    assert abs(np.dot(view.up, view.front)) < 1e-6


def test_a_real_fit_records_the_busts_up(laurana_bundle):
    view = laurana_bundle.manifest["view"]
    assert angle_deg(view["up"], REAL_UP["laurana-bust/laurana.ply"]) < 15
    assert view["up_source"] == "base plane"
    assert angle_deg(view["front"], (0, 0, 1)) < 30  # her face, seen in the renders


def test_a_relief_askew_in_its_frame_stands_with_its_edges_level():
    from fitter.fitting.examples import relief_scan

    points = relief_scan(6000)
    view = orient.find_view(Scan.from_array(points))
    assert view.up_source == "convention (relief)"
    axes = orient.flat_frame(points)
    assert min(angle_deg(view.up, axes[0]), angle_deg(view.up, axes[1])) < 1e-6
    assert angle_deg(view.front, axes[2]) < 1e-6 or angle_deg(view.front, -axes[2]) < 1e-6


# ------------------------------------------------------------- the gallery's thumbnail
def _thumbnail(tmp_path, scan: Scan, **options):
    import io

    from PIL import Image

    from fitter.server.thumbnail import render_thumbnail

    bundle = fit_scan(scan, tmp_path / "b", FitOptions(grid=(10, 10), method="linear", patches=1,
                                                       detail_levels=0, **options))
    png = render_thumbnail((bundle.path / "base.tsp").read_bytes(), bundle.manifest["view"])
    return np.asarray(Image.open(io.BytesIO(png))).astype(float) / 255  # (H, W, RGBA)


def test_the_thumbnail_shows_the_front_with_up_on_top(tmp_path):
    """A cone standing on its base along +z: seen from the front with up on top, its silhouette
    is a triangle, widest at the bottom; forced upside down it is widest at the top."""
    upright = _thumbnail(tmp_path / "a", cone_on_base(2, 1.0))[..., 3]
    rows = np.flatnonzero(upright.sum(axis=1) > 0)
    width = upright.sum(axis=1)
    top, bottom = rows[: len(rows) // 4], rows[-len(rows) // 4:]
    assert width[bottom].mean() > 2.5 * width[top].mean()
    flipped = _thumbnail(tmp_path / "b", cone_on_base(2, 1.0), up="-z")[..., 3]
    width = flipped.sum(axis=1)
    rows = np.flatnonzero(width > 0)
    assert width[rows[: len(rows) // 4]].mean() > 2.5 * width[rows[-len(rows) // 4:]].mean()


def test_the_thumbnail_has_no_pinholes_inside_the_object(tmp_path):
    """Supersampled and box-filtered, the far side never shows through the near one: inside the
    silhouette (eroded by 3 px) every pixel is fully covered, and no pixel is much darker than
    its 3 x 3 neighbourhood's median (the old cards' dotted moire)."""
    from scipy import ndimage

    card = _thumbnail(tmp_path, cone_on_base(2, 1.0))
    alpha, grey = card[..., 3], card[..., :3].mean(axis=2)
    inside = ndimage.binary_erosion(alpha > 0.5, iterations=3)
    assert inside.sum() > 5000
    assert alpha[inside].min() > 0.99
    dark = grey < ndimage.median_filter(grey, size=3) - 0.05
    assert dark[inside].mean() < 0.002
