"""Stanford range-scan alignment (``.conf``): register the listed scans into one cloud.

The Stanford 3D Scanning Repository ships raw range scans with a ``.conf``
written by scanalyze (Curless & Levoy 1996)::

    camera tx ty tz qi qj qk qr
    mesh   NAME tx ty tz qi qj qk qr
    bmesh  NAME tx ty tz qi qj qk qr

Each ``bmesh`` line places one scan file (resolved next to the ``.conf``; a
``NAME.gz`` is used when only the compressed file is present) in the common
frame by a translation ``t`` and a unit quaternion ``q = (qi, qj, qk, qr)``
(vector part first). The mapping is

    p_world = R(q)^T p + t,

with ``R(q)`` the usual rotation matrix of ``q`` (the one
``scipy.spatial.transform.Rotation.from_quat([qi, qj, qk, qr])`` gives), i.e.
the rotation by the conjugate quaternion: scanalyze stores the matrix for row
vectors. This was settled on the data, not assumed: on the Happy Buddha
(``happyStandRight_0`` / ``_24``) the median nearest-neighbour distance between
registered neighbouring scans is 0.23 mm (the sampling step) with this
reading, against 4.2 mm for ``R p + t``, 4.2 mm for ``R (p + t)`` and 0.44 mm
for ``R^T (p + t)``; ``tests/test_io.py`` checks it. The ``camera`` line is the
viewer's camera and does not move the data. ``mesh`` lines name scanalyze's
own raw scans (e.g. Cyberware ``_cybcyl`` cylinders, no PLY), which are not
read; each is reported in ``source["warnings"]``.

The result is a cloud: overlapping range images are not one mesh (their sheets lie on
top of each other, a fraction of the sampling step apart), so the scans' own triangles,
from a mesh PLY or a raw ``range_grid``, are dropped once there are two or more of them.
A ``.conf`` placing a single scan keeps that scan's faces.

The listed names are input too (``fitter.fitting.io.limits``): each must lie inside the
``.conf``'s folder (no absolute name, no ``..``, no link leading out), may be named once,
and there may be at most ``max_files`` of them; all the scans share the read's one
``InputBudget``, so their points and decompressed bytes count together. These checks
run on every line before the first scan is read (:func:`check_registration`, which the
upload checks call as well).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .limits import InputBudget, confined_path
from .scan import Scan, ScanError, make_scan, new_source
from .source import HashedInput


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix ``R`` (3, 3) of the quaternion ``q = (x, y, z, w)``, normalised first.

    ``R = I + 2 w [v]_x + 2 [v]_x^2`` for the unit quaternion ``(v, w)``
    (rotation of column vectors, ``p' = q p q*``).
    """
    q = np.asarray(q, np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm == 0:
        raise ValueError(f"quaternion must be finite and non-zero, got {q.tolist()}")
    x, y, z, w = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def parse_conf(text: str, name: str) -> tuple[list[tuple[str, np.ndarray, np.ndarray]], list[str]]:
    """``([(scan name, t (3,), q (4,) as x y z w)], skipped mesh names)`` of a ``.conf``."""
    entries: list[tuple[str, np.ndarray, np.ndarray]] = []
    skipped: list[str] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        key = words[0]
        expected = {"camera": 8, "mesh": 9, "bmesh": 9}.get(key)
        if expected is None:
            raise ScanError(f"{name}: line {lineno}: unknown keyword {key!r} (a Stanford .conf "
                            "has camera, mesh and bmesh lines)")
        if len(words) != expected:
            raise ScanError(f"{name}: line {lineno}: {key} needs {expected - 1} fields, got "
                            f"{len(words) - 1}: {line.strip()!r}")
        try:
            numbers = np.array([float(w) for w in words[-7:]])
        except ValueError:
            raise ScanError(f"{name}: line {lineno}: expected 7 numbers (tx ty tz qi qj qk qr) "
                            f"in {line.strip()!r}") from None
        if not np.all(np.isfinite(numbers)) or not np.any(numbers[3:]):
            raise ScanError(f"{name}: line {lineno}: translation and quaternion must be finite "
                            f"and the quaternion non-zero, got {numbers.tolist()}")
        if key == "bmesh":
            entries.append((words[1], numbers[:3], numbers[3:]))
        elif key == "mesh":
            skipped.append(words[1])
    return entries, skipped


def _resolve(directory: Path, scan_name: str, conf_name: str) -> Path:
    path = confined_path(directory, scan_name, conf_name)
    for candidate in (path, path.with_name(path.name + ".gz")):
        if candidate.is_file():
            return candidate
    raise ScanError(f"{conf_name}: lists scan {scan_name!r}, but neither {path} nor "
                    f"{path.name}.gz exists")


def check_registration(path: Path, entries: list[tuple[str, np.ndarray, np.ndarray]],
                       budget: InputBudget) -> list[Path]:
    """The file of each ``bmesh`` entry of the ``.conf`` at ``path``, each confined to its
    folder and counted by ``budget.take_file``.

    Raises
    ------
    ScanError
        No entries, a name outside the folder, a file that does not exist, a file named
        twice, more than ``max_files`` files.
    """
    if not entries:
        raise ScanError(f"{path.name}: the file lists no scans (no 'bmesh NAME tx ty tz qi qj "
                        "qk qr' lines)")
    files = []
    for scan_name, _, _ in entries:
        file = _resolve(path.parent, scan_name, path.name)
        budget.take_file(path.name, Path(os.path.realpath(file)))
        files.append(file)
    return files


def read_conf(path: Path, gzipped: bool, budget: InputBudget
              ) -> tuple[list[tuple[str, np.ndarray, np.ndarray]], list[str], dict]:
    """``(entries, skipped mesh names, the file's record)`` of the ``.conf`` at ``path``
    (see :func:`parse_conf`), read within ``budget``."""
    with HashedInput(path, gzipped, budget) as inp:
        data = inp.stream.read()
        record = inp.finish()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise ScanError(f"{path.name}: not a text .conf file") from None
    listed = sum(line.lstrip().startswith("bmesh") for line in text.splitlines())
    if listed > budget.limits.max_files:  # counted before any line is parsed
        raise budget.limits.refusal(path.name, f"names {listed:,} scan files", "max_files",
                                    f"{budget.limits.max_files:,}")
    entries, skipped = parse_conf(text, path.name)
    return entries, skipped, record


def load_conf(path: Path, gzipped: bool, budget: InputBudget,
              load_one) -> Scan:  # noqa: ANN001 - the loader
    """Load every ``bmesh`` scan of a ``.conf`` with ``load_one(path)`` (which shares
    ``budget``) and register them; every listed name is checked first
    (:func:`check_registration`)."""
    name = path.name
    entries, skipped, record = read_conf(path, gzipped, budget)
    listed = check_registration(path, entries, budget)
    points, normals, colors, files, scans, units = [], [], [], [record], [], set()
    faces = None
    for (scan_name, t, q), file in zip(entries, listed, strict=True):
        scan = load_one(file)
        rot = quaternion_matrix(q)
        points.append(scan.points @ rot + t)  # rows: (R^T p)^T = p^T R
        normals.append(None if scan.normals is None else scan.normals @ rot)
        colors.append(scan.colors)
        faces = scan.faces  # kept only for a single scan: see the module docstring
        files += [dict(f, role="scan") for f in scan.source["files"]]
        units.add(scan.units)
        scans.append({"name": scan_name, "file": scan.source["name"], "points": scan.n_points,
                      "translation": t.tolist(), "quaternion_xyzw": q.tolist()})

    def joined(arrays: list) -> np.ndarray | None:
        return np.concatenate(arrays) if all(a is not None for a in arrays) else None

    source = new_source(name, str(path), "conf", "gzip" if gzipped else None, "conf")
    source.update(bytes=record["bytes"], sha256=record["sha256"], files=files, scans=scans,
                  registration="p_world = R(q)^T p + t, q = (qi, qj, qk, qr)",
                  hash_method="sha256 of each file as stored; bytes/sha256 are the .conf's own")
    source["warnings"] += [f"'mesh {m}' line skipped: not a scan file this reader loads"
                           for m in skipped]
    return make_scan(name, np.concatenate(points), normals=joined(normals),
                     colors=joined(colors), faces=faces if len(entries) == 1 else None,
                     units=units.pop() if len(units) == 1 else "unknown", source=source)
