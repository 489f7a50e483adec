"""Gallery thumbnails: the base patch rendered on the server, small and shaded, and cached.

The patch is tessellated by ``client_py`` (the same evaluator as the browser),
viewed orthographically along its direction of least extent (the third
principal axis of the vertices, oriented towards the side the normals face),
and its vertices are splatted into a z-buffer with Lambert shading; one
dilation pass closes the pinholes between splats. It is a point-splatting
renderer, good for a 320-pixel card and a thousand times cheaper than a GPU.

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
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass

import numpy as np
from PIL import Image

from client_py import PatchFormatError, read_patch, tessellate_grid
from client_py.format import read_header

from ..collection.bundles import Bundle, BundleError

WIDTH, HEIGHT = 320, 240
GRID = 400  # vertices per side: about two per pixel across the card (fixed: bounds the work)
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


def _shade(positions: np.ndarray, normals: np.ndarray) -> Image.Image:
    """The card: ``positions`` and ``normals`` of shape ``(n, 3)`` splatted as described above.

    Raises
    ------
    ValueError
        When the vertices are not finite or span no area (nothing to draw).
    """
    if not np.isfinite(positions).all() or not np.isfinite(normals).all():
        raise ValueError("the surface has non-finite vertices or normals")
    centre = positions.mean(axis=0)
    _, _, axes = np.linalg.svd(positions - centre, full_matrices=False)
    e1, e2, e3 = axes
    if (normals @ e3).mean() < 0.0:
        e3 = -e3
    if np.linalg.det(np.stack([e1, e2, e3])) < 0.0:
        e2 = -e2  # keep a right-handed view so the image is not mirrored
    rel = positions - centre
    x, y, depth = rel @ e1, rel @ e2, rel @ e3
    if np.ptp(x) <= 0.0 or np.ptp(y) <= 0.0:
        raise ValueError("the surface spans no area (a point or a line): nothing to draw")
    span = max((x.max() - x.min()) / (WIDTH * 0.9), (y.max() - y.min()) / (HEIGHT * 0.9), 1e-12)
    px = np.clip(((x - 0.5 * (x.max() + x.min())) / span + WIDTH / 2).astype(int), 0, WIDTH - 1)
    py = np.clip((HEIGHT / 2 - (y - 0.5 * (y.max() + y.min())) / span).astype(int), 0,
                 HEIGHT - 1)
    # A raking key light from the upper left (how reliefs are photographed) and a soft fill.
    key = -0.6 * e1 + 0.6 * e2 + 0.53 * e3
    key /= np.linalg.norm(key)
    facing = np.where((normals @ e3)[:, None] < 0.0, -normals, normals)  # two-sided
    intensity = 0.2 + 0.62 * np.clip(facing @ key, 0.0, None) + 0.25 * np.clip(facing @ e3, 0, None)
    rgba = np.zeros((HEIGHT, WIDTH, 4), dtype=np.float64)
    order = np.argsort(depth)  # nearest last: later writes win
    rgba[py[order], px[order], :3] = intensity[order, None] * STONE
    rgba[py[order], px[order], 3] = 255.0
    hole = rgba[..., 3] == 0
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        shifted = np.roll(rgba, (dy, dx), axis=(0, 1))
        fill = hole & (shifted[..., 3] > 0)
        rgba[fill] = shifted[fill]
        hole &= ~fill
    return Image.fromarray(rgba.astype(np.uint8), "RGBA")


def render_thumbnail(patch: bytes) -> bytes:
    """PNG bytes (``WIDTH`` x ``HEIGHT``, RGBA) of the patch file's bytes ``patch``.

    Raises
    ------
    client_py.PatchFormatError
        When the bytes are not a valid patch, or it has more than
        :data:`MAX_CONTROL_POINTS` control points.
    ValueError
        When the surface is degenerate (see :func:`_shade`).
    """
    n_u, n_v = read_header(patch)["shape"]
    if n_u * n_v > MAX_CONTROL_POINTS:
        raise PatchFormatError(10, f"grid {n_u}x{n_v} has more than the {MAX_CONTROL_POINTS} "
                                   "control points a thumbnail is drawn for")
    surface = read_patch(patch).to_scan_frame()
    mesh = tessellate_grid(surface, GRID, GRID)
    positions = np.frombuffer(mesh.positions, dtype=np.float32).reshape(-1, 3).astype(float)
    normals = np.frombuffer(mesh.normals, dtype=np.float32).reshape(-1, 3).astype(float)
    image = _shade(positions, normals)
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
    """The thumbnail of ``bundle``'s base patch, or the reason it has none (bad, unsafe or
    too large a file, a degenerate surface: each a message naming the file, never its bytes)."""
    try:
        patch, _ = bundle.read_file(bundle.base_file, MAX_PATCH_BYTES)
        return Thumbnail(render_thumbnail(patch))
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
