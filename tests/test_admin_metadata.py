"""The admin edits an object's title, description, units and first view (up, front) after
its fit, and the public pages and the served manifest show the edits (issue 14); refusals are
a 400 in JSON naming the field."""

from __future__ import annotations

import json
import math
import re
import shutil

import numpy as np
import pytest
from conftest import ADMIN_TOKEN

from fitter.collection.catalog import Catalog, orthonormal_view, parse_direction

BEARER = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


@pytest.fixture()
def adopted(tmp_path, admin_app_factory, web_collection):
    """An admin app over a collection holding a copy of relief (adopted and published)."""
    collection = tmp_path / "collection"
    shutil.copytree(web_collection / "relief", collection / "relief",
                    ignore=shutil.ignore_patterns("error.ply", "error.png"))
    return admin_app_factory(collection, PROPAGATE_EXCEPTIONS=False)


def _served(client) -> dict:
    response = client.get("/bundles/relief/manifest.json")
    assert response.status_code == 200
    return json.loads(response.get_data())


def _patch(client, **fields):
    return client.patch("/admin/api/objects/relief", headers=BEARER, json=fields)


def test_each_field_edited_reaches_the_served_manifest_and_the_pages(adopted):
    client = adopted.test_client()
    fitted = _served(client)
    assert fitted["view"]["up_source"] != "admin" and fitted["description"] == ""
    for field, value in (("title", "A carved relief with a title long enough to wrap twice"),
                         ("description", "Limestone.\nFound in 1911."), ("units", "cm")):
        response = _patch(client, **{field: value})
        assert response.status_code == 200, response.get_json()
        assert response.get_json()[field] == value
        assert _served(client)[field] == value
    viewer = client.get("/objects/relief/").get_data(as_text=True)
    assert "A carved relief with a title long enough to wrap twice</h1>" in viewer
    assert 'class="description">Limestone.\nFound in 1911.</p>' in viewer
    assert re.search(r'id="fact-units">cm<', viewer)
    listed = client.get("/api/objects").get_json()[0]
    assert (listed["units"], listed["description"]) == ("cm", "Limestone.\nFound in 1911.")
    # up and front: unit vectors, front made perpendicular to up
    response = _patch(client, up=[0, 0, 2], front=[1, 0, 1])
    assert response.status_code == 200, response.get_json()
    view = _served(client)["view"]
    assert view == {"up": [0, 0, 1], "front": [1, 0, 0], "up_source": "admin",
                    "front_source": "admin"}
    assert response.get_json()["view"] == view
    # up alone: paired with the current front, which loses its part along the new up
    _patch(client, up=[1, 1, 0])
    view = _served(client)["view"]
    up, front = np.array(view["up"]), np.array(view["front"])
    assert np.linalg.norm(up) == pytest.approx(1, abs=1e-6)
    assert np.linalg.norm(front) == pytest.approx(1, abs=1e-6)
    assert up @ front == pytest.approx(0, abs=1e-6)
    np.testing.assert_allclose(up, [math.sqrt(0.5)] * 2 + [0], atol=1e-6)
    np.testing.assert_allclose(front, [math.sqrt(0.5), -math.sqrt(0.5), 0], atol=1e-6)
    # null: back to the fit's view
    assert _patch(client, up=None).status_code == 200
    assert _served(client)["view"] == fitted["view"]


def test_the_edited_manifest_is_revalidated_not_immutable(adopted):
    client = adopted.test_client()
    first = client.get("/bundles/relief/manifest.json")
    assert "immutable" not in first.headers["Cache-Control"]
    assert "no-cache" in first.headers["Cache-Control"] and first.headers["ETag"]
    again = client.get("/bundles/relief/manifest.json",
                       headers={"If-None-Match": first.headers["ETag"]})
    assert again.status_code == 304
    _patch(client, title="Renamed")
    changed = client.get("/bundles/relief/manifest.json",
                         headers={"If-None-Match": first.headers["ETag"]})
    assert changed.status_code == 200 and json.loads(changed.data)["title"] == "Renamed"
    # the other bundle files are still immutable, and the manifest gzipped when accepted
    assert "immutable" in client.get("/bundles/relief/base.tsp").headers["Cache-Control"]
    zipped = client.get("/bundles/relief/manifest.json", headers={"Accept-Encoding": "gzip"})
    assert zipped.headers["Content-Encoding"] == "gzip"


@pytest.mark.parametrize("fields, message", [
    ({"up": "sideways"}, "up must be three finite numbers"),
    ({"up": [0, 1]}, "up must be three finite numbers"),
    ({"up": [0, True, 0]}, "up must be three finite numbers"),
    ({"front": "1e999 0 0"}, "front must be three finite numbers"),
    ({"up": [0, 0, 0]}, "up must not be zero"),
    ({"front": [0, 0, 0]}, "front must not be zero"),
    ({"up": [0, 1, 0], "front": [0, -3, 0.01]}, "front must not be parallel to up"),
    ({"title": ""}, "title must not be empty"),
    ({"title": 12}, "title must be text"),
    ({"units": "u" * 21}, "units is 21 characters long; at most 20"),
    ({"units": "m\nm"}, "units must be one line of text"),
    ({"description": "d" * 10_001}, "description is 10001 characters long; at most 10000"),
])
def test_a_bad_value_is_a_400_in_json_naming_the_field(adopted, fields, message):
    client = adopted.test_client()
    before = _served(client)
    response = _patch(client, **fields)
    assert response.status_code == 400 and response.is_json
    assert message in response.get_json()["error"]
    assert _served(client) == before  # nothing changed


def test_the_admin_page_edits_the_view_and_a_title_edit_leaves_it_alone(adopted):
    from test_admin import csrf_of, login

    client = adopted.test_client()
    login(client)
    page = client.get("/admin/objects/relief").get_data(as_text=True)
    shown_up = re.search(r'name="up" value="([^"]*)"', page).group(1)
    shown_front = re.search(r'name="front" value="([^"]*)"', page).group(1)
    token = csrf_of(client, "/admin/objects/relief")
    form = {"csrf_token": token, "title": "Relief", "description": "", "provenance": "",
            "licence": "", "units": "", "up": shown_up, "front": shown_front}
    assert client.post("/admin/objects/relief", data=form).status_code == 302
    assert _served(client)["view"]["up_source"] != "admin"  # the fit's, not re-stated
    assert client.post("/admin/objects/relief",
                       data={**form, "up": "+z", "front": "-x"}).status_code == 302
    assert _served(client)["view"]["up"] == [0, 0, 1]
    assert _served(client)["view"]["front"] == [-1, 0, 0]
    refused = client.post("/admin/objects/relief", data={**form, "up": "+z", "front": "+z"})
    assert refused.status_code == 400
    assert "front must not be parallel to up" in refused.get_data(as_text=True)


def test_the_thumbnail_follows_an_edited_view(adopted):
    client = adopted.test_client()
    first = client.get("/objects/relief/thumbnail.png")
    assert first.status_code == 200
    _patch(client, up=[0, 0, 1], front=[1, 0, 0])
    turned = client.get("/objects/relief/thumbnail.png")
    assert turned.status_code == 200 and turned.headers["ETag"] != first.headers["ETag"]
    assert turned.data != first.data


def test_directions_are_read_and_made_orthonormal():
    assert parse_direction("-y", "up") == (0.0, -1.0, 0.0)
    assert parse_direction(" 1, 2 3 ", "up") == (1.0, 2.0, 3.0)
    view = orthonormal_view((0.0, 2.0, 0.0), (1.0, 1.0, 0.0))
    assert view == {"up": [0.0, 1.0, 0.0], "front": [1.0, 0.0, 0.0]}


def test_the_catalog_migration_adds_the_view_column(tmp_path):
    with Catalog(tmp_path / "c", create=True) as catalog:
        columns = {r[1] for r in catalog.conn.execute("PRAGMA table_info(objects)")}
        assert "view" in columns


# ------------------------------------------------------------------ .conf registrations
def _range_ply(path, points: np.ndarray) -> None:
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\n"
            "property float y\nproperty float z\nend_header\n")
    path.write_text(head + "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in points))


def test_a_conf_registration_shows_every_file_read_and_its_points(tmp_path):
    from fitter.fitting.examples import relief_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan
    from fitter.server import create_app

    scans = tmp_path / "scans"
    scans.mkdir()
    points = relief_scan(6_000, seed=2)
    middle = np.median(points[:, 0])
    halves = (points[points[:, 0] < middle], points[points[:, 0] >= middle])
    for k, half in enumerate(halves):
        _range_ply(scans / f"part_{k}.ply", half)
    (scans / "object.conf").write_text("camera 0 0 0 0 0 0 1\n" + "".join(
        f"bmesh part_{k}.ply 0 0 0 0 0 0 1\n" for k in range(2)))
    collection = tmp_path / "collection"
    bundle = fit_scan(scans / "object.conf", collection / "conf",
                      FitOptions(grid=(10, 10), detail_levels=0))
    read = sum(p.stat().st_size for p in scans.iterdir())
    assert bundle.manifest["provenance"]["bytes"] == (scans / "object.conf").stat().st_size
    client = create_app({"TESSERA_COLLECTION": str(collection), "TESTING": True,
                         "TESSERA_PYODIDE_SNAPSHOT": False}).test_client()
    listed = client.get("/api/objects/conf").get_json()
    assert listed["scan"] == {"bytes": read, "points": 6_000, "files": 3}
    viewer = client.get("/objects/conf/").get_data(as_text=True)
    expected = f"6,000 scan points, {read / 1024:.1f} KB in 3 files"
    assert re.search(rf'id="fact-source">{re.escape(expected)}<', viewer), viewer
    gallery = client.get("/").get_data(as_text=True)
    assert f"(scan: {read / 1024:.1f} KB)" in gallery and "6,000 points" in gallery



def test_an_atlas_bundle_takes_the_same_edits_and_its_thumbnail_follows(tmp_path,
                                                                         admin_app_factory):
    """Atlases are the default for closed objects: the admin's edits reach their served
    manifest, gallery card and thumbnail as a single patch's do."""
    from atlas_bundle import write_atlas_bundle

    collection = tmp_path / "collection"
    write_atlas_bundle(collection / "relief", k=1, levels=1, base_resolution=5)
    client = admin_app_factory(collection, PROPAGATE_EXCEPTIONS=False).test_client()
    fitted = _served(client)
    assert fitted["format_version"] == 2
    before = client.get("/objects/relief/thumbnail.png").data
    response = _patch(client, title="A sphere of six patches", units="cm",
                      description="An atlas.", up=[1, 0, 0], front=[0, 0, 1])
    assert response.status_code == 200, response.get_json()
    served = _served(client)
    assert (served["title"], served["units"], served["description"]) == \
        ("A sphere of six patches", "cm", "An atlas.")
    assert served["view"]["up"] == [1, 0, 0] and served["view"]["up_source"] == "admin"
    assert served["base"] == fitted["base"] and served["tiles"] == fitted["tiles"]
    gallery = client.get("/").get_data(as_text=True)
    assert "A sphere of six patches" in gallery and "atlas of 6 patches" in gallery
    after = client.get("/objects/relief/thumbnail.png")
    assert after.status_code == 200 and after.data != before
