"""Shared pytest fixtures for the Tessera test suite."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# The seconds a test page waits for Pyodide, for every app the suite starts (in-process or a
# `tessera serve` child): the product's 45 s is for a visitor, and a shared 2-core machine
# running the suite has taken over 45 s to start Pyodide under load. Tests of the timeout
# itself set their own.
os.environ.setdefault("TESSERA_PYODIDE_TIMEOUT", "180")

PROJECT_ROOT = Path(__file__).resolve().parent.parent
#: the real scans, read in place (never copied into the repo): ../shared/data from the root
SHARED_DATA = PROJECT_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` relative to the project root; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real scans not available: {SHARED_DATA} does not exist")
    return SHARED_DATA


@pytest.fixture(scope="session")
def laurana_bundle(shared_data: Path, tmp_path_factory: pytest.TempPathFactory):
    """The Laurana bust fitted once with default options (an atlas bundle with colour): the
    one real default fit of a bust that several tests read (its colour, its recorded view)."""
    import fcntl
    import json
    import os

    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import Bundle, fit_scan

    path = shared_data / "laurana-bust" / "laurana.ply"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    # made once per run: pytest-xdist's workers share their base folder's parent, and the
    # first to take the lock fits (a worker whose fit failed leaves no manifest: refitted)
    shared = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = shared.parent
    bundle = shared / "laurana-default-fit"
    with open(shared / "laurana-default-fit.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (bundle / "manifest.json").is_file():
            return fit_scan(path, bundle, FitOptions())
    return Bundle(bundle, json.loads((bundle / "manifest.json").read_text()))


@pytest.fixture
def fit_layout_calls(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The layout triangle counts ``fitter.fitting.atlas.fit.fit_layout`` is called with,
    in order, while the test runs (the atlas fit's trials and refits, counted)."""
    from fitter.fitting.atlas import fit as atlas_fit

    calls: list[int] = []
    real_fit_layout = atlas_fit.fit_layout

    def counted(layout, *args, **kwargs):
        calls.append(layout.n_triangles)
        return real_fit_layout(layout, *args, **kwargs)

    monkeypatch.setattr(atlas_fit, "fit_layout", counted)
    return calls


# ------------------------------------------------------------- web server and browser (issue 5)
@pytest.fixture(scope="session")
def web_collection(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A collection of two bundles: ``relief``, fitted from the generated relief scan (20x20
    grid), and ``corrupt``, the same with one byte of ``base.tsp`` flipped."""
    import shutil

    from fitter.fitting.examples import relief_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    root = tmp_path_factory.mktemp("collection")
    fit_scan(relief_scan(20_000), root / "relief",
             FitOptions(grid=(20, 20), title="Carved relief (generated example)"))
    shutil.copytree(root / "relief", root / "corrupt")
    patch = root / "corrupt" / "base.tsp"
    data = bytearray(patch.read_bytes())
    data[len(data) // 2] ^= 0xFF
    patch.write_bytes(bytes(data))
    return root


@pytest.fixture(scope="session")
def web_app(web_collection: Path):
    from fitter.server import create_app

    app = create_app({"TESSERA_COLLECTION": str(web_collection), "TESTING": True})
    if app.extensions["tessera_snapshot"] is not None:
        app.extensions["tessera_snapshot"].ensure()  # pages start Pyodide from it (cached)
    return app


@pytest.fixture(scope="session")
def live_server(web_app):
    """The app on 127.0.0.1 and an OS-chosen port, in a background thread."""
    from live import LiveServer

    with LiveServer(web_app) as live:
        yield live


@pytest.fixture(scope="session")
def browser_type_launch_args(browser_type_launch_args: dict) -> dict:
    """pytest-playwright launches Debian's Chromium (never a downloaded build)."""
    from live import CHROMIUM_PATH, chromium_launch_args

    if not Path(CHROMIUM_PATH).exists():
        pytest.skip(f"{CHROMIUM_PATH} is missing: `make chromium` installs Debian's chromium")
    launch = chromium_launch_args()
    del launch["headless"]  # pytest-playwright's --headed decides
    return {**browser_type_launch_args, **launch}


# ------------------------------------------------------------- admin area and batch fits (issue 7)
#: the admin secret the admin tests use (long enough for check_token_strength)
ADMIN_TOKEN = "test-admin-token-0123456789"


@pytest.fixture(scope="session")
def relief_ply(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The generated relief (20,000 points, synthetic) as a binary PLY file, as a scanner
    would write it."""
    from fitter.demo import write_scan_ply
    from fitter.fitting.examples import relief_scan

    path = tmp_path_factory.mktemp("scans") / "relief.ply"
    write_scan_ply(path, relief_scan(20_000))
    return path


@pytest.fixture()
def admin_app_factory(tmp_path: Path):
    """``make(**config) -> app``: an app with the admin area on (token :data:`ADMIN_TOKEN`)
    over a fresh empty collection folder ``tmp_path / 'collection'``."""
    from fitter.server import create_app

    def make(collection: Path | None = None, **config):
        root = collection or tmp_path / "collection"
        root.mkdir(exist_ok=True)
        settings = {"TESSERA_COLLECTION": str(root), "TESSERA_ADMIN_TOKEN": ADMIN_TOKEN,
                    "TESSERA_PYODIDE_SNAPSHOT": False, "TESTING": True}
        settings.update(config)
        return create_app(settings)

    return make


_EXIT_STATUS: dict[str, int] = {}


def pytest_sessionfinish(session, exitstatus):
    _EXIT_STATUS["status"] = int(exitstatus)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    """The test run ends as a command does (``fitter.process_exit.exit_now``: its exit status
    once the report is written, the C libraries' unload skipped, where glibc aborted after
    fits in 1 to 5 runs of 6). Only the run's own process: an xdist worker (``workerinput``)
    ends as xdist has it end."""
    if "status" in _EXIT_STATUS and not hasattr(config, "workerinput"):
        from fitter.process_exit import exit_now

        exit_now(_EXIT_STATUS["status"])
