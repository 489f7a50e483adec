"""Setuptools' ``build_py`` plus the viewer: a wheel carries web/ as ``fitter/server/web/``.

The server reads its templates, its JavaScript modules and the browser runtime
(Pyodide, three.js) from ``web/`` (``fitter.server.WEB_ROOT``). A source
checkout and an editable install read them in place; a wheel must carry them,
in the same layout under ``fitter/server/web/``, where ``fitter.server`` looks
first. Only what the server sends or runs is copied (:data:`WEB_FILES`), not
the 40 MB of ``web/node_modules``; the wheel is built from a checkout where
``npm ci`` has run in ``web/``, and the build stops, naming the file, when a
runtime file is missing. ``pyproject.toml`` names this command in
``[tool.setuptools.cmdclass]``; the sdist carries the same files.
"""

from __future__ import annotations

from pathlib import Path

from setuptools.command.build_py import build_py

#: ``web/`` in the checkout, and its place in the wheel.
WEB_SOURCE = "web"
WEB_PACKAGE_DIR = Path("fitter", "server", "web")

#: What the wheel carries, as globs relative to ``web/``; each must match a file.
WEB_FILES = (
    # our own: templates (fitter/server/*.py render them) and the modules served at /web/src/
    "templates/*.html",
    "src/*.js",
    "src/*.css",
    # run by node to make the Pyodide snapshot (fitter/server/snapshot.py)
    "tools/make-pyodide-snapshot.mjs",
    # /vendor/pyodide/: what loadPyodide fetches from its indexURL; package.json gives the
    # version the snapshot is keyed on
    "node_modules/pyodide/package.json",
    "node_modules/pyodide/pyodide.mjs",
    "node_modules/pyodide/pyodide.asm.mjs",
    "node_modules/pyodide/pyodide.asm.wasm",
    "node_modules/pyodide/python_stdlib.zip",
    "node_modules/pyodide/pyodide-lock.json",
    # /vendor/three/: the viewer's import map ("three", "three/addons/") and what they import
    "node_modules/three/LICENSE",
    "node_modules/three/build/three.module.js",
    "node_modules/three/build/three.core.js",
    "node_modules/three/examples/jsm/controls/OrbitControls.js",
    # pyodide.mjs imports ws when it runs in node (the snapshot); never served
    "node_modules/ws/LICENSE",
    "node_modules/ws/package.json",
    "node_modules/ws/*.js",
    "node_modules/ws/*.mjs",
    "node_modules/ws/lib/*.js",
)


def web_files(root: Path) -> tuple[list[Path], list[str]]:
    """``(files, missing)``: the files of :data:`WEB_FILES` under ``root / 'web'`` (relative to
    ``web/``), and the patterns that match none (``npm ci`` has not run in ``web/``)."""
    web = root / WEB_SOURCE
    files: list[Path] = []
    missing: list[str] = []
    for pattern in WEB_FILES:
        matches = sorted(p.relative_to(web) for p in web.glob(pattern) if p.is_file())
        files += matches
        if not matches:
            missing.append(pattern)
    return files, missing


class BuildPyWithWeb(build_py):
    """``build_py`` that also copies :data:`WEB_FILES` to ``fitter/server/web/`` in the build.

    An editable install copies nothing: its server reads the checkout's ``web/``.
    Paths are relative to the project root, the working directory of every build.
    """

    def run(self) -> None:
        super().run()
        if self.editable_mode:
            return
        files, missing = web_files(Path())
        if missing:
            raise FileNotFoundError(
                f"{WEB_SOURCE}/{missing[0]}: no such file ({len(missing)} of the viewer's "
                f"patterns match nothing); run `npm ci` in {WEB_SOURCE}/ before building a wheel")
        for name in files:
            target = Path(self.build_lib) / WEB_PACKAGE_DIR / name
            self.mkpath(str(target.parent))
            self.copy_file(str(Path(WEB_SOURCE) / name), str(target))

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        outputs = super().get_outputs(include_bytecode)
        if self.editable_mode:
            return outputs
        files, _ = web_files(Path())
        return outputs + [str(Path(self.build_lib) / WEB_PACKAGE_DIR / name) for name in files]

    def get_source_files(self) -> list[str]:
        """The sources plus the web files present, so that an sdist builds the same wheel
        (egg_info asks this of every build, editable ones too: no error for what is missing)."""
        files, _ = web_files(Path())
        return super().get_source_files() + [str(Path(WEB_SOURCE) / name) for name in files]
