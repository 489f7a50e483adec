"""The serving process loads no fit: scipy stays out of ``sys.modules`` while it serves.

A fresh interpreter (so nothing this test process imported counts) builds the app over a
collection of one fitted bundle with the admin area on, and requests every kind of page:
the gallery, the viewer, a bundle file, the JSON API, the thumbnail, the admin login page
and, logged in through its form, the admin upload page, and the admin API with a Bearer
token. Then it reports what it imported.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

from conftest import ADMIN_TOKEN

SERVE_SCRIPT = r"""
import json, re, sys
from fitter.server import create_app

app = create_app({"TESSERA_COLLECTION": sys.argv[1], "TESSERA_PYODIDE_SNAPSHOT": False,
                  "TESTING": True})
client = app.test_client()
status = {}
for url in ("/", "/objects/relief/", "/bundles/relief/base.tsp", "/bundles/relief/manifest.json",
            "/api/objects", "/api/objects/relief", "/objects/relief/thumbnail.png",
            "/admin/login"):
    status[url] = client.get(url).status_code
login = client.get("/admin/login").get_data(as_text=True)
csrf = re.search(r'name="csrf_token" value="([^"]+)"', login).group(1)
status["POST /admin/login"] = client.post(
    "/admin/login", data={"token": sys.argv[2], "csrf_token": csrf, "next": ""}).status_code
status["/admin/upload"] = client.get("/admin/upload").status_code
status["/admin/ (logged in)"] = client.get("/admin/").status_code
bearer = app.test_client()
status["/admin/api/objects (Bearer)"] = bearer.get(
    "/admin/api/objects", headers={"Authorization": f"Bearer {sys.argv[2]}"}).status_code
print(json.dumps({
    "status": status,
    "scipy": sorted(m for m in sys.modules if m == "scipy" or m.startswith("scipy.")),
    "fitting": sorted(m for m in sys.modules if m.startswith("fitter.fitting")),
}))
"""


def test_the_public_server_and_the_admin_pages_import_no_scipy(web_collection, tmp_path):
    collection = tmp_path / "collection"
    shutil.copytree(web_collection / "relief", collection / "relief")
    environ = {**os.environ, "TESSERA_ADMIN_TOKEN": ADMIN_TOKEN}  # the admin area is on
    done = subprocess.run([sys.executable, "-c", SERVE_SCRIPT, str(collection), ADMIN_TOKEN],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path, env=environ)
    assert done.returncode == 0, done.stderr[-4000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    expected = {url: 200 for url in report["status"]}
    expected["POST /admin/login"] = 302  # to the admin area, session cookie set
    assert report["status"] == expected
    assert "scipy" not in report["scipy"], (
        f"the serving process imported scipy; fit modules loaded: {report['fitting']}")
