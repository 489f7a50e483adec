"""Gallery thumbnails: the base patch rendered on the server, small and shaded, and cached.

An atlas bundle (manifest version 2, ``base.tsa``) is drawn the same way from its welded
mesh (:func:`render_atlas_thumbnail`), the splats sized by the mesh's edges; a patch's
detached pieces (``pieces.tsa``, docs/format.md "Pieces") are drawn with it as the viewer
draws them (:func:`pieces_of`), so the card shows what the visitor's browser draws.

The patch is tessellated by ``client_py`` (the same evaluator as the browser) and viewed
orthographically from the front the viewer starts at: along the manifest's ``view.front``
with ``view.up`` up (``fitter.fitting.orient``; a bundle without ``view``: along the
vertices' direction of least extent, oriented towards the side the normals face). The drawn
vertices (those the triangles use: trimmed cells are off the object) are splatted into a
z-buffer :data:`SUPERSAMPLE` times the card's size with Lambert shading, each covering a
square as wide as the gap to its grid neighbours (so the near surface hides the far one
everywhere: single pixels of the back showing through were the old cards' dotted moire),
and the image is reduced by a box filter (the mean of each ``SUPERSAMPLE`` x ``SUPERSAMPLE``
block, colour weighted by coverage, alpha the coverage). A point-splatting renderer, good
for a 320-pixel card and a thousand times cheaper than a GPU.

A thumbnail costs a decode and a ``GRID`` x ``GRID`` tessellation, so the work is bounded
and remembered: the base file is read only through :meth:`Bundle.read_file` (inside the
bundle, a regular file, at most :data:`MAX_PATCH_BYTES` and the size the manifest records),
a patch of more than :data:`MAX_CONTROL_POINTS` control points is refused from its header
before it is decoded, and :class:`ThumbnailCache` keeps the outcome — the PNG or the
reason there is none — per version of the file (bundle, name, mtime, size, inode) in an LRU
bounded in entries and bytes. At most :data:`RENDERS_AT_ONCE` renders run at a time, and
concurrent requests for the same version wait for one render instead of repeating it.
"""

from __future__ import annotations

import io
import math
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass

import numpy as np
from PIL import Image

from client_py import PatchFormatError, read_patch, tessellate_grid
from client_py.atlas_format import read_atlas
from client_py.atlas_mesh import tessellate_atlas
from client_py.bundle import ATLAS_MAX_RESOLUTION, Mesh, pieces_entry, read_pieces
from client_py.format import read_header
from client_py.mesh_arrays import mesh_arrays

from ..collection.bundles import Bundle, BundleError

WIDTH, HEIGHT = 320, 240
GRID = 400  # vertices per side: about two per pixel across the card (fixed: bounds the work)
SUPERSAMPLE = 3  # rendered at 3x the card's size, then box-filtered down
MAX_SPLAT = 3  # the largest splat half-width, in supersampled pixels
#: the largest base file read for a thumbnail (a 1024 x 1024 patch is a few MB)
MAX_PATCH_BYTES = 32 << 20
#: the largest patch drawn: the fitter's largest grid, 1024 x 1024 control points
MAX_CONTROL_POINTS = 1024 * 1024
#: what the cache holds at most
CACHE_ENTRIES = 512
CACHE_BYTES = 32 << 20
#: thumbnails rendered at the same time (each may take a second of CPU)
RENDERS_AT_ONCE = 2
STONE = np.array([222.0, 212.0, 196.0])
BACKGROUND = (0, 0, 0, 0)


def _view_axes(positions: np.ndarray, normals: np.ndarray,
               view: dict | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Screen right ``e1``, up ``e2`` and towards-the-viewer ``e3`` (unit, right-handed): from
    the manifest's ``view`` (``e2 = up``, ``e3 = front`` made perpendicular to it), else the
    principal axes of the vertices, ``e3`` the least, on the side the normals face.

    Raises
    ------
    ValueError
        A ``view`` whose ``up`` or ``front`` is not three finite numbers, or parallel.
    """
    if view is not None:
        try:
            up = np.array(view["up"], dtype=np.float64)
            front = np.array(view["front"], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"manifest view must have up and front [x, y, z], got "
                             f"{view!r:.200}") from None
        if up.shape != (3,) or front.shape != (3,) or not (np.isfinite(up).all()
                                                            and np.isfinite(front).all()):
            raise ValueError(f"manifest view up and front must be 3 finite numbers each, got "
                             f"{view!r:.200}")
        if not np.linalg.norm(up) > 0:
            raise ValueError(f"manifest view up must not be zero, got {view['up']!r:.80}")
        e2 = up / np.linalg.norm(up)
        e3 = front - (front @ e2) * e2
        if not np.linalg.norm(e3) > 1e-6:
            raise ValueError(f"manifest view front must not be parallel to up, got "
                             f"{view!r:.200}")
        e3 /= np.linalg.norm(e3)
        return np.cross(e2, e3), e2, e3
    centre = positions.mean(axis=0)
    _, _, axes = np.linalg.svd(positions - centre, full_matrices=False)
    e1, e2, e3 = axes
    if (normals @ e3).mean() < 0.0:
        e3 = -e3
    if np.linalg.det(np.stack([e1, e2, e3])) < 0.0:
        e2 = -e2  # keep a right-handed view so the image is not mirrored
    return e1, e2, e3


def _splat_radius(sx: np.ndarray, sy: np.ndarray) -> np.ndarray:
    """Half-width ``(rows * cols,)`` of each grid vertex's splat, in pixels: half the largest
    screen distance to its next neighbour along either grid direction, rounded up, in
    ``1..MAX_SPLAT``; ``sx``, ``sy`` the screen coordinates as ``(rows, cols)`` grids."""
    gap = np.zeros(sx.shape)
    for axis in (0, 1):
        step = np.hypot(np.diff(sx, axis=axis), np.diff(sy, axis=axis))
        gap = np.maximum(gap, np.pad(step, [(0, 1) if a == axis else (0, 0) for a in (0, 1)],
                                     mode="edge"))
    return np.clip(np.ceil(gap.ravel() / 2), 1, MAX_SPLAT).astype(int)


def _edge_splat_radius(px: np.ndarray, py: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Half-width of each vertex's splat for a mesh that is no grid (an atlas): half its
    longest incident edge on screen, rounded up, in ``1..MAX_SPLAT``; ``triangles`` of shape
    ``(T, 3)`` index ``px``, ``py``."""
    ends = np.concatenate([triangles[:, [a, b]] for a, b in ((0, 1), (1, 2), (2, 0))])
    length = np.hypot(*(np.subtract(*c[ends].T) for c in (px, py)))
    order = np.argsort(length, kind="stable")
    gap = np.zeros(len(px))
    for side in (0, 1):  # repeated indices: the last write, the longest edge, wins
        gap[ends[order, side]] = length[order]
    return np.clip(np.ceil(gap / 2), 1, MAX_SPLAT).astype(int)


def _shade(positions: np.ndarray, normals: np.ndarray, drawn: np.ndarray, grid: int,
           view: dict | None = None, triangles: np.ndarray | None = None,
           pieces: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> Image.Image:
    """The card: the ``grid x grid`` tessellation's ``positions`` and ``normals`` of shape
    ``(grid^2, 3)``, of which the vertices ``drawn`` (indices) are splatted as described above.
    With ``triangles`` (``(T, 3)`` indices into ``positions``: a mesh that is no grid, of
    which every vertex is drawn) the splats are sized by the triangles' edges instead.
    ``pieces``: the ``positions``, ``normals`` and ``triangles`` of a mesh drawn with it (a
    patch's detached pieces), every vertex splatted, sized by its triangles' edges.

    Raises
    ------
    ValueError
        When the vertices are not finite or span no area (nothing to draw), or ``view`` is
        invalid (:func:`_view_axes`).
    """
    positions, normals = positions[drawn], normals[drawn]  # checked where drawn only
    own = len(positions)  # the vertices after these are the pieces'
    if pieces is not None:
        positions, normals = (np.concatenate([a, b]) for a, b in zip((positions, normals),
                                                                     pieces[:2], strict=True))
    if not np.isfinite(positions).all() or not np.isfinite(normals).all():
        raise ValueError("the surface has non-finite vertices or normals")
    e1, e2, e3 = _view_axes(positions, normals, view)
    rel = positions - positions.mean(axis=0)
    x, y, depth = rel @ e1, rel @ e2, rel @ e3
    if np.ptp(x) <= 0.0 or np.ptp(y) <= 0.0:
        raise ValueError("the surface spans no area (a point or a line): nothing to draw")
    width, height = WIDTH * SUPERSAMPLE, HEIGHT * SUPERSAMPLE
    span = max((x.max() - x.min()) / (width * 0.9), (y.max() - y.min()) / (height * 0.9), 1e-12)
    px = np.rint((x - 0.5 * (x.max() + x.min())) / span + width / 2).astype(int)
    py = np.rint(height / 2 - (y - 0.5 * (y.max() + y.min())) / span).astype(int)
    if triangles is not None:
        radius = _edge_splat_radius(px[:own], py[:own], triangles)
    else:
        # the splat sizes come from the whole grid (neighbours of drawn vertices may be trimmed)
        full_x = np.zeros(grid * grid)
        full_y = np.zeros(grid * grid)
        full_x[drawn], full_y[drawn] = px[:own], py[:own]
        radius = _splat_radius(full_x.reshape(grid, grid), full_y.reshape(grid, grid))[drawn]
    if pieces is not None:
        radius = np.concatenate([radius, _edge_splat_radius(px[own:], py[own:], pieces[2])])
    # A raking key light from the upper left (how reliefs are photographed) and a soft fill.
    key = -0.6 * e1 + 0.6 * e2 + 0.53 * e3
    key /= np.linalg.norm(key)
    facing = np.where((normals @ e3)[:, None] < 0.0, -normals, normals)  # two-sided
    intensity = 0.2 + 0.62 * np.clip(facing @ key, 0.0, None) + 0.25 * np.clip(facing @ e3, 0, None)
    cells, depths, values = [], [], []
    for r in range(1, MAX_SPLAT + 1):
        these = radius == r
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                qx, qy = px[these] + dx, py[these] + dy
                inside = (qx >= 0) & (qx < width) & (qy >= 0) & (qy < height)
                cells.append((qy * width + qx)[inside])
                depths.append(depth[these][inside])
                values.append(intensity[these][inside])
    cell, order = np.concatenate(cells), np.argsort(np.concatenate(depths), kind="stable")
    rgba = np.zeros((height * width, 4), dtype=np.float64)
    rgba[cell[order], :3] = np.concatenate(values)[order, None] * STONE  # nearest last wins
    rgba[cell[order], 3] = 255.0
    blocks = rgba.reshape(HEIGHT, SUPERSAMPLE, WIDTH, SUPERSAMPLE, 4)
    alpha = blocks[..., 3].sum(axis=(1, 3))
    colour = ((blocks[..., :3] * blocks[..., 3:]).sum(axis=(1, 3))
              / np.maximum(alpha, 1e-9)[..., None])
    card = np.concatenate([colour, (alpha / SUPERSAMPLE**2)[..., None]], axis=-1)
    return Image.fromarray(np.clip(np.rint(card), 0, 255).astype(np.uint8), "RGBA")


def _normals(mesh) -> np.ndarray:
    return np.frombuffer(mesh.normals, dtype=np.float32).reshape(-1, 3).astype(float)


def render_thumbnail(patch: bytes, view: dict | None = None, pieces: Mesh | None = None
                     ) -> bytes:
    """PNG bytes (``WIDTH`` x ``HEIGHT``, RGBA) of the patch file's bytes ``patch``, seen from
    the manifest's ``view`` (``None``: a bundle without one, see the module's docstring), with
    its detached ``pieces`` as drawn (:func:`pieces_of`) when it has some.

    Raises
    ------
    client_py.PatchFormatError
        When the bytes are not a valid patch, or it has more than
        :data:`MAX_CONTROL_POINTS` control points.
    ValueError
        When the surface is degenerate or ``view`` invalid (see :func:`_shade`).
    """
    n_u, n_v = read_header(patch)["shape"]
    if n_u * n_v > MAX_CONTROL_POINTS:
        raise PatchFormatError(10, f"grid {n_u}x{n_v} has more than the {MAX_CONTROL_POINTS} "
                                   "control points a thumbnail is drawn for")
    surface = read_patch(patch).to_scan_frame()
    mesh = tessellate_grid(surface, GRID, GRID)
    positions, triangles = mesh_arrays(mesh)
    drawn = np.unique(triangles)
    if len(drawn) == 0:
        raise ValueError("the patch draws no triangles: nothing to draw")
    shown = None
    if pieces is not None:
        piece_positions, piece_triangles = mesh_arrays(pieces)
        shown = (piece_positions, _normals(pieces), piece_triangles)
    image = _shade(positions, _normals(mesh), drawn, GRID, view, pieces=shown)
    out = io.BytesIO()
    image.save(out, format="PNG", optimize=True)
    return out.getvalue()


def _atlas_resolution(patches: int, drawn: int = ATLAS_MAX_RESOLUTION) -> int:
    """Samples per patch side of an atlas of ``patches`` drawn for a card: about ``GRID^2``
    vertices in all, as a patch's grid, at least 2 a side and at most ``drawn`` (what the
    viewer draws it at)."""
    return min(drawn, max(2, int(math.sqrt(GRID * GRID / patches))))


def pieces_of(bundle: Bundle) -> Mesh | None:
    """A patch bundle's detached pieces as the viewer draws them (``client_py.bundle.
    read_pieces``, docs/format.md "Pieces"), at most :func:`_atlas_resolution`'s samples a
    patch side (the work bounded as an atlas's); ``None`` without pieces, or when their
    entry or file cannot be read: the patch is then drawn alone, as the viewer does."""
    try:
        pieces = read_pieces(bundle.manifest,
                             lambda name: bundle.read_file(name, MAX_PATCH_BYTES)[0])
        if pieces is None:
            return None
        drawn = pieces_entry(bundle.manifest)["resolution"]
        return tessellate_atlas(pieces, _atlas_resolution(len(pieces.quads), drawn))
    except (BundleError, PatchFormatError, ValueError):  # ValueError: a collapsed patch
        return None


def render_atlas_thumbnail(data: bytes, view: dict | None = None) -> bytes:
    """PNG bytes of an atlas bundle's ``base.tsa`` (manifest version 2), seen from ``view``:
    the atlas tessellated by ``client_py.atlas_mesh.tessellate_atlas`` at the same samples
    per patch side for all, about ``GRID^2`` vertices in all as for a patch (at least 2 a
    side, at most ``client_py.bundle.ATLAS_MAX_RESOLUTION``), splatted like a patch's grid.

    Raises
    ------
    client_py.PatchFormatError
        When the bytes are not a valid atlas (sizes bounded by its header before decoding).
    ValueError
        When the surface is degenerate or ``view`` invalid (see :func:`_shade`).
    """
    atlas, _ = read_atlas(data)
    mesh = tessellate_atlas(atlas, _atlas_resolution(len(atlas.quads)))
    positions, triangles = mesh_arrays(mesh)
    image = _shade(positions, _normals(mesh), np.arange(len(positions)), 0, view, triangles)
    out = io.BytesIO()
    image.save(out, format="PNG", optimize=True)
    return out.getvalue()


@dataclass(frozen=True)
class Thumbnail:
    """The outcome of one thumbnail: ``png`` bytes, or ``error`` saying why there are none."""

    png: bytes | None
    error: str | None = None

    @property
    def nbytes(self) -> int:
        return len(self.png or b"") + len(self.error or "") + 200  # + the entry's own keep


def thumbnail_of(bundle: Bundle) -> Thumbnail:
    """The thumbnail of ``bundle``'s base (a patch with its detached pieces, an atlas), or
    the reason it has none (bad, unsafe or too large a file, a degenerate surface: each a
    message naming the file, never its bytes)."""
    try:
        patch, _ = bundle.read_file(bundle.base_file, MAX_PATCH_BYTES)
        view = bundle.manifest.get("view")
        if bundle.base_file.endswith(".tsa"):
            return Thumbnail(render_atlas_thumbnail(patch, view))
        return Thumbnail(render_thumbnail(patch, view, pieces_of(bundle)))
    except BundleError as exc:
        return Thumbnail(None, str(exc))
    except PatchFormatError as exc:
        return Thumbnail(None, f"{bundle.id}/{bundle.base_file}: {exc}")
    except ValueError as exc:
        return Thumbnail(None, f"{bundle.id}/{bundle.base_file}: no thumbnail: {exc}")


class ThumbnailCache:
    """Thumbnails by a key naming one version of a file, least recently used evicted first.

    Parameters
    ----------
    max_entries, max_bytes : int
        Bounds on the number of thumbnails kept and on their total size
        (:attr:`Thumbnail.nbytes`).
    renders_at_once : int
        Renders allowed to run at the same time; other requests wait for a turn.
    """

    def __init__(self, max_entries: int = CACHE_ENTRIES, max_bytes: int = CACHE_BYTES,
                 renders_at_once: int = RENDERS_AT_ONCE) -> None:
        if max_entries < 1 or max_bytes < 1 or renders_at_once < 1:
            raise ValueError(f"max_entries, max_bytes and renders_at_once must be >= 1, got "
                             f"{max_entries}, {max_bytes}, {renders_at_once}")
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self.renders = 0  # how many times ``make`` ran (the tests read it)
        self._entries: OrderedDict[Hashable, Thumbnail] = OrderedDict()
        self._bytes = 0
        self._pending: dict[Hashable, threading.Lock] = {}
        self._lock = threading.Lock()
        self._turns = threading.BoundedSemaphore(renders_at_once)

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def nbytes(self) -> int:
        return self._bytes

    def _lookup(self, key: Hashable) -> Thumbnail | None:
        with self._lock:
            hit = self._entries.get(key)
            if hit is not None:
                self._entries.move_to_end(key)
            return hit

    def get(self, key: Hashable, make: Callable[[], Thumbnail]) -> Thumbnail:
        """The thumbnail kept under ``key``, else ``make()``'s, kept (successes and failures)."""
        hit = self._lookup(key)
        if hit is not None:
            return hit
        with self._lock:
            pending = self._pending.setdefault(key, threading.Lock())
        try:
            with pending:  # one render per key; the others wait for it and read the cache
                hit = self._lookup(key)
                if hit is not None:
                    return hit
                with self._turns:
                    self.renders += 1
                    made = make()
                self._keep(key, made)
                return made
        finally:
            with self._lock:
                self._pending.pop(key, None)

    def _keep(self, key: Hashable, thumbnail: Thumbnail) -> None:
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self._bytes -= old.nbytes
            if thumbnail.nbytes > self.max_bytes:
                return  # larger than the whole cache: answered, not kept
            self._entries[key] = thumbnail
            self._bytes += thumbnail.nbytes
            while len(self._entries) > self.max_entries or self._bytes > self.max_bytes:
                _, evicted = self._entries.popitem(last=False)
                self._bytes -= evicted.nbytes
