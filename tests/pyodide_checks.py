"""client_py checks that run inside Pyodide (and, for the comparison, in CPython).

Pyodide's npm package has no pytest and no numpy offline, so this is a plain
script, standard library only. ``tests/pyodide_runner.mjs`` runs it with the
global ``INPUT`` (reference values computed in CPython with scipy, written as
JSON by ``tests/test_pyodide.py``) and reads back ``RESULT``:

    {"kernel": ..., "checks": {name: error message or None},
     "digests": {name: sha256 of bytes client_py produced}}

The digests (tessellated arrays, PLY and .tsp bytes, all from the pure-Python
kernel) are compared with the same script's digests in CPython: the browser
must produce the very same bytes.
"""

from __future__ import annotations

import hashlib
import math

from client_py import (
    DetailTile,
    NurbsSurface,
    PatchFormatError,
    TrimMask,
    read_detail_tile,
    read_patch,
    tessellate_grid,
    tessellate_region,
    write_detail_tile,
    write_patch,
    write_ply,
)
from client_py._kernel import KERNEL_NAME


def _surface(spec: dict) -> NurbsSurface:
    trim = TrimMask(spec["trim"]) if spec.get("trim") else None
    return NurbsSurface(tuple(spec["degree"]), tuple(spec["knots"]), spec["control_points"],
                        spec["weights"], trim=trim, metadata=spec.get("metadata"))


def _max_diff(a, b) -> float:
    return max(abs(x - y) for pa, pb in zip(a, b, strict=True)
               for x, y in zip(pa, pb, strict=True))


def _sha(data) -> str:
    return hashlib.sha256(bytes(data)).hexdigest()


def _check(checks: dict, name: str, func) -> None:
    """Record ``None`` when ``func`` passes, else the failure (any exception) as text."""
    try:
        func()
        checks[name] = None
    except Exception as exc:  # noqa: BLE001 - every failure is reported, by name
        checks[name] = f"{type(exc).__name__}: {exc}"


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise AssertionError(message)


def _lcg_values(count: int, seed: int, spread: int) -> list[int]:
    """Deterministic pseudo-random integers in ``-spread..spread`` (no ``random`` module
    state to share between interpreters), mostly small as detail coefficients are."""
    out, x = [], seed
    for _ in range(count):
        x = (1103515245 * x + 12345) % 2**31
        out.append((x % (2 * spread + 1) - spread) // (1 + (x >> 20) % 4))
    return out


def _detail_checks(checks: dict, digests: dict) -> None:
    """Detail tiles (range-coded .tsd) and region tessellation give CPython's bytes."""
    mask = TrimMask([[(r * 7 + c * 3) % 5 != 0 for c in range(8)] for r in range(8)])
    tiles = [DetailTile(1, i, j, 2, 6, 0.015625, tuple(_lcg_values(64, 11 * i + j + 1, 40)),
                        mask if (i, j) == (1, 0) else None) for i in range(2) for j in range(2)]
    blobs = [write_detail_tile(t) for t in tiles]
    for k, data in enumerate(blobs):
        digests[f"tile{k}.tsd"] = _sha(data)

    def tile_round_trip():
        for tile, data in zip(tiles, blobs, strict=True):
            _require(read_detail_tile(data) == tile, f"tile {tile.i}_{tile.j} changed")
            for cut in range(0, len(data), 5):
                try:
                    read_detail_tile(data[:cut])
                except PatchFormatError:
                    continue
                raise AssertionError(f"tile truncated to {cut} bytes was accepted")

    _check(checks, "detail tiles round trip; truncations raise PatchFormatError",
           tile_round_trip)
    U = [0, 0, 0, 0.5, 1, 1, 1]
    grid = [[[i / 3, j / 3, 0.1 * ((i * j) % 3)] for j in range(4)] for i in range(4)]
    trim = TrimMask([[not (2 <= r <= 4 and 1 <= c <= 5) for c in range(8)] for r in range(8)])
    base = NurbsSurface((2, 2), (U, U), grid, trim=trim)
    mesh = tessellate_region(base, (0.25, 0.0, 1.0, 0.75), 23, 19, tiles, kernel="python")
    for name in ("positions", "normals", "uvs", "indices"):
        digests[f"region.{name}"] = _sha(memoryview(getattr(mesh, name)).cast("B"))


def run(spec: dict) -> dict:
    checks: dict = {}
    digests: dict = {}
    for k, case in enumerate(spec["cases"]):
        s = _surface(case["surface"])
        pts = case["params"]

        def evaluate(s=s, pts=pts, case=case):
            got = [s.evaluate(u, v) for u, v in pts]
            err = _max_diff(got, case["oracle_points"])
            _require(err <= 1e-10, f"evaluate differs from scipy by {err}")
            nrm = [s.normal(u, v) for u, v in pts]
            err = _max_diff(nrm, case["oracle_normals"])
            _require(err <= 1e-9, f"normal differs from scipy by {err}")

        _check(checks, f"case{k}: evaluate and normal match scipy", evaluate)
        nu, nv = case["grid"]
        mesh = tessellate_grid(s, nu, nv, kernel="python")
        for name in ("positions", "normals", "uvs", "indices"):
            digests[f"case{k}.{name}"] = _sha(memoryview(getattr(mesh, name)).cast("B"))

        def grid_positions(mesh=mesh, case=case):
            ref = case["oracle_grid"]
            got = [mesh.positions[3 * i : 3 * i + 3] for i in range(len(ref))]
            err = _max_diff(got, ref)
            scale = max(1.0, max(abs(c) for p in ref for c in p))
            _require(err <= 2.0**-23 * scale, f"grid positions differ from scipy by {err}")

        _check(checks, f"case{k}: tessellated grid matches scipy", grid_positions)
        digests[f"case{k}.ply_binary"] = _sha(write_ply(mesh, texture_file="t.png"))
        digests[f"case{k}.ply_ascii"] = _sha(write_ply(mesh, binary=False))
        data = write_patch(s, bits=case["bits"])
        digests[f"case{k}.tsp"] = _sha(data)

        def round_trip(s=s, data=data, case=case, k=k):
            r = read_patch(data)
            _require(r.knots == s.knots, "knots changed")
            _require(r.trim == s.trim and r.metadata == s.metadata, "trim or metadata changed")
            half_step = 1.0 / (2 * (2 ** case["bits"] - 1))
            for axis in range(3):
                a, b = s.flat_points[axis::3], r.flat_points[axis::3]
                err = max(abs(x - y) for x, y in zip(a, b, strict=True))
                _require(err <= half_step * (max(a) - min(a)) * (1 + 1e-9),
                         f"axis {axis} off by {err}")
            digests[f"case{k}.tsp_decoded"] = _sha(repr((r.flat_points, r.flat_weights)).encode())

        _check(checks, f"case{k}: patch round trip", round_trip)

        def corruption(data=data):
            for cut in range(len(data)):
                try:
                    read_patch(data[:cut])
                except PatchFormatError:
                    continue
                raise AssertionError(f"truncation to {cut} bytes was accepted")
            for offset in range(0, len(data), 7):
                flipped = bytearray(data)
                flipped[offset] ^= 0x41
                try:
                    read_patch(bytes(flipped))
                except PatchFormatError:
                    continue
                raise AssertionError(f"a change at byte {offset} was accepted")

        _check(checks, f"case{k}: truncated and changed files raise PatchFormatError", corruption)

    def quarter_circle():
        c = math.sqrt(0.5)
        s = NurbsSurface((2, 1), ([0, 0, 0, 1, 1, 1], [0, 0, 1, 1]),
                         [[[2, 0, 0], [2, 0, 1]], [[2, 2, 0], [2, 2, 1]], [[0, 2, 0], [0, 2, 1]]],
                         [[1, 1], [c, c], [1, 1]])
        mesh = tessellate_grid(s, 33, 2, kernel="python")
        for i in range(0, len(mesh.positions), 3):
            r = math.hypot(mesh.positions[i], mesh.positions[i + 1])
            _require(abs(r - 2.0) <= 4e-7, f"vertex {i // 3} at radius {r}")
        for u in (0.0, 0.1, 0.5, 0.77, 1.0):
            x, y, _ = s.evaluate(u, 0.5)
            _require(abs(math.hypot(x, y) - 2.0) <= 1e-12, f"radius at u={u}")

    _check(checks, "quarter cylinder is an exact circle", quarter_circle)

    def rejects_bad_input():
        U = [0, 0, 0, 1, 1, 1]
        grid = [[[i, j, 0] for j in range(3)] for i in range(3)]
        for kwargs, word in (({"knots": ([0, 0, 1, 1], U)}, "knots[0] (U) has 4 knots"),
                             ({"weights": [[1, 1, 1], [1, -1, 1], [1, 1, 1]]}, "weights[1][1]")):
            args = {"degree": (2, 2), "knots": (U, U), "control_points": grid} | kwargs
            try:
                NurbsSurface(**args)
            except ValueError as exc:
                _require(word in str(exc), f"message {exc!r} lacks {word!r}")
            else:
                raise AssertionError(f"{kwargs} was accepted")

    _check(checks, "invalid input raises ValueError naming it", rejects_bad_input)
    _detail_checks(checks, digests)
    return {"kernel": KERNEL_NAME, "checks": checks, "digests": digests}


if "INPUT" in globals() and INPUT is not None:  # noqa: F821 - set by pyodide_runner.mjs
    RESULT = run(INPUT)  # noqa: F821
