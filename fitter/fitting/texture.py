"""The texture pyramid: the scan's colour resampled into the patch's ``(u, v)`` space.

Colour comes from what the scan has: a UV-textured mesh (``bali-mask``: every
texel of the patch domain takes the scan texture's colour at the texture
coordinate interpolated from the triangle it falls in), per-vertex colours of
a mesh (``laurana-bust``: interpolated over the triangles) or of a point cloud
(each point splatted into its texel). Triangles are rasterised in the domain
at the foot points ``(u, v)`` of their vertices (``fitter.fitting.error.deviations``),
only those with three covered vertices (the front the patch represents) and,
on a periodic map, not across the seam. Texels no triangle or point reaches
are filled by push-pull (Gortler et al., *The Lumigraph*, SIGGRAPH 1996: a
pyramid of coverage-weighted averages, then coarse values pushed into the
holes), so bilinear filtering and mip-mapping near the rim never fetch black.

Level ``k`` is the domain at ``size 2^k`` texels per side cut into
``2^k x 2^k`` images of ``size x size`` (the detail quadtree's rectangles),
each written as WebP (or PNG) through Pillow with row 0 at the top
(``v`` up, see ``client_py.layers.TextureImage``). The number of levels follows
the source: no finer than the colour samples the scan has over the covered
part of the domain. Tiles with no sample of their own are not written.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

TILE_SIZE = 256
MAX_LEVELS = 4
WEBP_QUALITY = 82


@dataclass
class TextureTile:
    level: int
    i: int
    j: int
    data: bytes
    ext: str
    size: int = TILE_SIZE


def _splat(u: np.ndarray, v: np.ndarray, rgb: np.ndarray, res: int
           ) -> tuple[np.ndarray, np.ndarray]:
    x = np.minimum((u * res).astype(np.int64), res - 1)
    y = np.minimum((v * res).astype(np.int64), res - 1)
    cell = x * res + y
    weight = np.bincount(cell, minlength=res * res).astype(float)
    total = np.stack([np.bincount(cell, rgb[:, c], res * res) for c in range(3)], axis=1)
    return total.reshape(res, res, 3), weight.reshape(res, res)


def _rasterise(uv: np.ndarray, faces: np.ndarray, attrs: np.ndarray, res: int,
               max_box: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric interpolation of per-vertex ``attrs (N, C)`` over triangles ``faces``
    drawn at ``uv (N, 2)`` on a ``res x res`` grid (texel ``(x, y)`` centred at
    ``((x + 1/2) / res, (y + 1/2) / res)``). Returns the sum and the count per texel.
    Vectorised over triangles, one pass per offset inside their bounding boxes;
    triangles spanning more than ``max_box`` texels (fold-overs at a rim) are left out."""
    p = uv * res - 0.5
    a, b, c = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
    den = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
    lo = np.ceil(np.minimum(np.minimum(a, b), c)).astype(np.int64).clip(0, res - 1)
    hi = np.floor(np.maximum(np.maximum(a, b), c)).astype(np.int64).clip(0, res - 1)
    width = hi - lo + 1
    good = (np.abs(den) > 1e-12) & (width <= max_box).all(axis=1) & (width > 0).all(axis=1)
    a, b, c, den, faces, lo, width = (x[good] for x in (a, b, c, den, faces, lo, width))
    channels = attrs.shape[1]
    total = np.zeros((res * res, channels))
    count = np.zeros(res * res)
    for dx in range(int(width[:, 0].max(initial=0))):
        for dy in range(int(width[:, 1].max(initial=0))):
            sel = np.flatnonzero((width[:, 0] > dx) & (width[:, 1] > dy))
            x, y = lo[sel, 0] + dx, lo[sel, 1] + dy
            A, B, C, D = a[sel], b[sel], c[sel], den[sel]
            la = ((B[:, 1] - C[:, 1]) * (x - C[:, 0]) + (C[:, 0] - B[:, 0]) * (y - C[:, 1])) / D
            lb = ((C[:, 1] - A[:, 1]) * (x - C[:, 0]) + (A[:, 0] - C[:, 0]) * (y - C[:, 1])) / D
            lc = 1.0 - la - lb
            inside = (la >= -1e-9) & (lb >= -1e-9) & (lc >= -1e-9)
            if not inside.any():
                continue
            w = np.stack([la[inside], lb[inside], lc[inside]], axis=1)
            value = np.einsum("tk,tkc->tc", w, attrs[faces[sel[inside]]])
            cell = x[inside] * res + y[inside]
            for ch in range(channels):
                total[:, ch] += np.bincount(cell, value[:, ch], res * res)
            count += np.bincount(cell, minlength=res * res)
    return total.reshape(res, res, channels), count.reshape(res, res)


def push_pull(colour_sum: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Fill texels of zero ``weight``: ``colour_sum (R, R, C)`` / ``weight (R, R)`` where
    covered, else the coverage-weighted average of the nearest coarser level that has one
    (pull by 2x2 sums, push back down). ``R`` a power of two."""
    if weight.shape[0] <= 1:
        return colour_sum / np.maximum(weight, 1e-12)[..., None]
    r = weight.shape[0]
    coarse_sum = colour_sum.reshape(r // 2, 2, r // 2, 2, -1).sum(axis=(1, 3))
    coarse_w = weight.reshape(r // 2, 2, r // 2, 2).sum(axis=(1, 3))
    coarse = push_pull(coarse_sum, coarse_w)
    up = np.repeat(np.repeat(coarse, 2, axis=0), 2, axis=1)
    own = colour_sum / np.maximum(weight, 1e-12)[..., None]
    return np.where((weight > 0)[..., None], own, up)


def sample_image(image: np.ndarray, tex_uv: np.ndarray) -> np.ndarray:
    """Bilinear RGB of ``image (H, W, 3)`` at texture coordinates ``(s, t)`` with ``t`` up
    (OBJ/trimesh convention: ``t = 0`` the bottom row), repeating outside ``[0, 1]``."""
    h, w = image.shape[:2]
    x = (tex_uv[:, 0] % 1.0) * w - 0.5
    y = (1.0 - tex_uv[:, 1] % 1.0) * h - 0.5
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0c, x1c = np.clip(x0, 0, w - 1), np.clip(x0 + 1, 0, w - 1)
    y0c, y1c = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    img = image.astype(float)
    top = img[y0c, x0c] * (1 - fx) + img[y0c, x1c] * fx
    bottom = img[y1c, x0c] * (1 - fx) + img[y1c, x1c] * fx
    return top * (1 - fy) + bottom * fy


def _usable_faces(faces: np.ndarray, covered: np.ndarray, u: np.ndarray,
                  periodic_u: bool) -> np.ndarray:
    keep = covered[faces].all(axis=1)
    if periodic_u:
        fu = u[faces]
        keep &= (fu.max(axis=1) - fu.min(axis=1)) < 0.5  # not across the seam
    return faces[keep]


def texture_levels(scan, covered: np.ndarray, max_levels: int, size: int = TILE_SIZE) -> int:
    """Levels the scan's colour supports: texels per side no more than its colour samples
    over the covered part (:func:`colour_samples`, :func:`texel_levels`); 0 without colour."""
    samples = colour_samples(scan, covered)
    if not samples:
        return 0
    return texel_levels(np.sqrt(max(samples, 1.0)), size, max_levels)


def colour_samples(scan, covered: np.ndarray) -> float:
    """The scan's colour samples over its ``covered`` points: texture texels through the
    UV area of the triangles of three covered vertices (a textured mesh), else the covered
    points (per-vertex colour); 0 without colour."""
    if scan.uv is not None and scan.texture is not None and scan.faces is not None:
        f = scan.faces[covered[scan.faces].all(axis=1)]
        t = scan.uv[f]
        area = 0.5 * np.abs((t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1])
                            - (t[:, 2, 0] - t[:, 0, 0]) * (t[:, 1, 1] - t[:, 0, 1])).sum()
        return float(area * scan.texture.size[0] * scan.texture.size[1])
    if scan.colors is not None:
        return float(covered.sum())
    return 0.0


def texel_levels(source_side: float, first_side: int, max_levels: int) -> int:
    """The one depth rule of a colour pyramid whose level ``k`` has ``first_side 2^k`` texels
    per side over a region where the scan has ``source_side^2`` colour samples: at least one
    level, and a finer one while its texels per side stay within ``source_side`` (never
    finer than the scan's colour), at most ``max_levels``."""
    levels = 1
    while levels < max_levels and first_side * 2**levels <= source_side:
        levels += 1
    return levels


def uv_picture(grid: np.ndarray) -> np.ndarray:
    """An image of ``grid (T_u, T_v, 3)`` (axis 0 ``u``, axis 1 ``v``) in the texture
    tiles' orientation (``client_py.layers.TextureImage``): ``u`` to the right, ``v`` up,
    so rows top-down run ``v`` falling; shape ``(T_v, T_u, 3)``."""
    return np.ascontiguousarray(grid.transpose(1, 0, 2)[::-1])


def encode_image(picture: np.ndarray, fmt: str = "webp", quality: int = WEBP_QUALITY) -> bytes:
    """``picture (H, W, 3) uint8`` (row 0 at the top) as WebP (``quality``, the slowest
    best method) or lossless PNG, through Pillow."""
    from PIL import Image

    buf = io.BytesIO()
    if fmt == "webp":
        Image.fromarray(picture).save(buf, "WEBP", quality=quality, method=6)
    elif fmt == "png":
        Image.fromarray(picture).save(buf, "PNG", optimize=True)
    else:
        raise ValueError(f"fmt must be 'webp' or 'png', got {fmt!r}")
    return buf.getvalue()


def has_colour(scan) -> bool:
    return scan.colors is not None or (scan.uv is not None and scan.texture is not None
                                       and scan.faces is not None)


def texture_pyramid(scan, u: np.ndarray, v: np.ndarray, covered: np.ndarray, levels: int,
                    periodic_u: bool = False, size: int = TILE_SIZE,
                    fmt: str = "webp") -> list[TextureTile]:
    """Texture tiles of levels ``0..levels-1`` from ``scan``'s colour at foot points
    ``u, v (N,)`` of its points (see the module docstring). Empty when the scan has
    no colour."""
    if levels <= 0 or not has_colour(scan):
        return []
    res = size << (levels - 1)
    uv = np.column_stack([u, v])
    faces = None if scan.faces is None else _usable_faces(scan.faces, covered, u, periodic_u)
    if scan.uv is not None and scan.texture is not None and faces is not None:
        tex_uv, count = _rasterise(uv, faces, scan.uv, res)
        where = count > 0
        colour = np.zeros((res, res, 3))
        image = np.asarray(scan.texture.convert("RGB"))
        colour[where] = sample_image(image, tex_uv[where] / count[where][:, None])
        total, weight = colour, where.astype(float)
    elif faces is not None and len(faces):
        total, weight = _rasterise(uv, faces, scan.colors[:, :3].astype(float), res)
    else:
        total, weight = _splat(u[covered], v[covered], scan.colors[covered, :3].astype(float),
                               res)
    full = np.clip(np.rint(push_pull(total, weight)), 0, 255).astype(np.uint8)
    seen = weight > 0
    tiles = []
    for k in range(levels):
        factor = 1 << (levels - 1 - k)
        r = res // factor
        img = full.reshape(r, factor, r, factor, 3).mean(axis=(1, 3)) if factor > 1 else full
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        hit = seen.reshape(r, factor, r, factor).any(axis=(1, 3))
        for i in range(1 << k):
            for j in range(1 << k):
                block = (slice(i * size, (i + 1) * size), slice(j * size, (j + 1) * size))
                if not hit[block].any():
                    continue
                picture = uv_picture(img[block])
                tiles.append(TextureTile(k, i, j, encode_image(picture, fmt), fmt, size))
    return tiles


def fit_texture(scan, dev, covered: np.ndarray, periodic_u: bool, max_levels: int,
                enabled: bool = True) -> list[TextureTile]:
    """The pipeline's texture stage: ``[]`` without colour (or when not ``enabled``), else
    :func:`texture_pyramid` over :func:`texture_levels` levels (at least one, at most
    ``max_levels`` and ``MAX_LEVELS``)."""
    if not enabled or not has_colour(scan):
        return []
    levels = texture_levels(scan, covered, max(1, min(max_levels, MAX_LEVELS)))
    return texture_pyramid(scan, dev.u, dev.v, covered, levels, periodic_u)
