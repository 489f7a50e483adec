"""Text point clouds: XYZ, PTS (Leica: a point count first) and ASC (CloudCompare), also ``.gz``.

One row per point, values separated by whitespace or by commas (decided on the
first data row), ``x y z`` first. The preamble may hold blank lines, comments
(``#`` or ``//``, where CloudCompare writes its column names, e.g.
``//X,Y,Z,R,G,B``), a header row of column names, and for PTS the point count.
The body goes through ``numpy.loadtxt`` (C parser) from the hashed stream in blocks of
``BLOCK_ROWS`` rows, each block's points counted against the read's ``max_points``
(``fitter.fitting.io.limits``) as it is parsed, so a cloud over the limit is refused
holding at most one block beyond it.

Extra columns are interpreted by name when a header names them (``nx ny nz`` /
``normal_x``..., ``r g b`` / ``red``..., ``intensity``/``i``), otherwise by the
layouts the common exporters write, accepted only when the values fit:

=========  ==========================================
columns    layouts tried, in order
=========  ==========================================
3          x y z
4          x y z intensity
6          x y z nx ny nz | x y z r g b
7          x y z intensity r g b (Leica PTS) | x y z intensity nx ny nz
9          x y z r g b nx ny nz (CloudCompare) | x y z nx ny nz r g b
10         x y z intensity r g b nx ny nz | x y z intensity nx ny nz r g b
=========  ==========================================

RGB must be whole numbers in 0..255 and normals unit length (within 1 %, or
zero); a table that fits no layout keeps ``x y z`` and lists the rest as
``extra`` in ``source["columns"]``. Intensity is read but not kept.
"""

from __future__ import annotations

import io
import itertools
import warnings
from pathlib import Path

import numpy as np

from .limits import InputBudget
from .scan import Scan, ScanError, make_scan, new_source, units_from_comments
from .source import GZIP_ERRORS, HashedInput

GROUPS = {"i": ("intensity",), "rgb": ("r", "g", "b"), "n": ("nx", "ny", "nz")}
LAYOUTS = {
    3: [()], 4: [("i",)], 6: [("n",), ("rgb",)], 7: [("i", "rgb"), ("i", "n")],
    9: [("rgb", "n"), ("n", "rgb")], 10: [("i", "rgb", "n"), ("i", "n", "rgb")],
}
NAME_ALIASES = {
    "x": "x", "y": "y", "z": "z",
    "nx": "nx", "ny": "ny", "nz": "nz",
    "normal_x": "nx", "normal_y": "ny", "normal_z": "nz",
    "r": "r", "g": "g", "b": "b", "red": "r", "green": "g", "blue": "b",
    "i": "intensity", "intensity": "intensity", "scalar_intensity": "intensity",
}
COMMENT_PREFIXES = ("#", "//")
BLOCK_ROWS = 1 << 17  # rows parsed at a time (about 3 MB of text for x y z)


def _tokens(line: str, delimiter: str | None) -> list[str]:
    return [t.strip() for t in line.split(delimiter)] if delimiter else line.split()


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _names(tokens: list[str]) -> list[str]:
    return [NAME_ALIASES.get(t.lower(), "extra") for t in tokens]


def _fits(group: str, values: np.ndarray) -> bool:
    if group == "rgb":
        return bool(np.all((values >= 0) & (values <= 255) & (values == np.rint(values))))
    if group == "n":
        norm = np.linalg.norm(values, axis=1)
        return bool(np.any(norm > 0) and np.all((np.abs(norm - 1) < 0.01) | (norm == 0)))
    return True


def guess_columns(values: np.ndarray) -> list[str]:
    """Column names for an unnamed table (see the module docstring's layout table)."""
    ncols = values.shape[1]
    for layout in LAYOUTS.get(ncols, []):
        names, col, ok = ["x", "y", "z"], 3, True
        for group in layout:
            width = len(GROUPS[group])
            ok = ok and _fits(group, values[:, col:col + width])
            names += GROUPS[group]
            col += width
        if ok:
            return names
    return ["x", "y", "z"] + ["extra"] * (ncols - 3)


def load_text(path: Path, gzipped: bool, budget: InputBudget | None = None, *,
              fmt: str) -> Scan:
    """Read an ``.xyz``, ``.pts`` or ``.asc`` text point cloud (see the module docstring);
    ``budget`` (default: the default ``InputLimits``) bounds the gzip stream and the rows."""
    name = path.name
    budget = budget if budget is not None else InputBudget()
    with HashedInput(path, gzipped, budget) as inp:
        text = io.TextIOWrapper(inp.stream, encoding="utf-8", newline=None)
        try:
            values, header, comments, declared = _read_table(text, name, fmt, budget)
        except UnicodeDecodeError as exc:
            raise ScanError(f"{name}: not a text point cloud (byte {exc.start} of a chunk is "
                            "not UTF-8 text)") from None
        except GZIP_ERRORS as exc:
            raise ScanError(f"{name}: corrupt gzip data: {exc}") from None
        finally:
            text.detach()
        record = inp.finish()
    if declared is not None and declared != values.shape[0]:
        raise ScanError(f"{name}: the PTS count line declares {declared} points but the file "
                        f"holds {values.shape[0]} point rows")
    names = header or guess_columns(values)
    if len(names) != values.shape[1]:
        raise ScanError(f"{name}: the header names {len(names)} columns but the rows have "
                        f"{values.shape[1]} values")
    if not {"x", "y", "z"} <= set(names):
        raise ScanError(f"{name}: the header names no x, y, z columns (got {header})")
    col = {n: i for i, n in reversed(list(enumerate(names)))}

    def pick(keys: tuple[str, ...]) -> np.ndarray | None:
        if not set(keys) <= set(col):
            return None
        return values[:, [col[k] for k in keys]]

    colors = pick(("r", "g", "b"))
    if colors is not None:
        if not _fits("rgb", colors):
            raise ScanError(f"{name}: the r g b columns must hold whole numbers 0..255")
        colors = colors.astype(np.uint8)
    source = new_source(name, str(path), fmt, "gzip" if gzipped else None, "text")
    source.update(bytes=record["bytes"], sha256=record["sha256"], files=[record],
                  hash_method="sha256 of the stored file, streamed in chunks while parsing",
                  columns=names, columns_named_by="header" if header else "layout")
    if "intensity" in names:  # as the E57 and LAS readers say it
        source["warnings"].append("intensity read but not kept (Scan has no intensity "
                                  "channel)")
    if "extra" in names:
        source["warnings"].append(f"{names.count('extra')} unrecognised columns were not kept")
    return make_scan(name, pick(("x", "y", "z")), normals=pick(("nx", "ny", "nz")),
                     colors=colors, units=units_from_comments(comments), source=source)


def _comments_of(block: list[str]) -> str | list[str]:
    """The comment prefixes to give ``loadtxt`` for ``block``: ``"#"`` alone (its C parser,
    several times faster) unless a line holds a ``/``, which no number does."""
    return list(COMMENT_PREFIXES) if any("/" in line for line in block) else "#"


def _read_table(text: io.TextIOWrapper, name: str, fmt: str, budget: InputBudget
                ) -> tuple[np.ndarray, list[str] | None, list[str], int | None]:
    """``(values (N, C), header names or None, comments, PTS count or None)``; every row
    counted against ``budget`` as its block is parsed."""
    comments: list[str] = []
    header: list[str] | None = None
    declared: int | None = None
    lineno = 0
    while True:
        line = text.readline()
        lineno += 1
        if not line:
            raise ScanError(f"{name}: the file contains no points (no numeric rows in "
                            f"{lineno - 1} lines)")
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith(COMMENT_PREFIXES):
            comment = stripped.lstrip("#/").strip()
            comments.append(comment)
            named = _names(_tokens(comment, "," if "," in comment else None))
            if header is None and {"x", "y", "z"} <= set(named):
                header = named
            continue
        delimiter = "," if "," in stripped else None
        tokens = _tokens(stripped, delimiter)
        if fmt == "pts" and declared is None and len(tokens) == 1 and tokens[0].isdigit():
            declared = int(tokens[0])
            if declared > budget.limits.max_points:  # refused before reading a row
                budget.take_points(name, declared)
            continue
        if all(_is_number(t) for t in tokens):
            break
        if not any(_is_number(t) for t in tokens) and header is None:
            header = _names(tokens)
            continue
        raise ScanError(f"{name}: line {lineno}: cannot read {stripped[:60]!r} as numbers")
    if len(tokens) < 3:
        raise ScanError(f"{name}: line {lineno}: a point needs at least x y z, got "
                        f"{len(tokens)} value(s): {stripped[:60]!r}")
    first = np.array([float(t) for t in tokens], dtype=np.float64)
    budget.take_points(name, 1)
    blocks = [first[None, :]]
    while block := list(itertools.islice(text, BLOCK_ROWS)):
        try:
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=".*input contained no data.*")
                rows = np.loadtxt(block, dtype=np.float64, delimiter=delimiter,
                                  comments=_comments_of(block), ndmin=2)
        except ValueError as exc:
            raise ScanError(f"{name}: unreadable point rows after line {lineno}: "
                            f"{exc}") from None
        if rows.size and rows.shape[1] != first.size:
            raise ScanError(f"{name}: line {lineno} has {first.size} values but the rows "
                            f"after it have {rows.shape[1]}")
        budget.take_points(name, rows.shape[0])  # at most one block past the limit
        blocks.append(rows.reshape(-1, first.size))
        lineno += len(block)
    values = np.concatenate(blocks) if len(blocks) > 1 else blocks[0]
    return values, header, comments, declared
