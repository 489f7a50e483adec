"""Colour of an atlas: per-patch texel cells packed into images, sampled at the vertices.

An atlas (``client_py.atlas``) has hundreds of patches, each with its own ``[0, 1]^2``.
Its colour at level ``c`` gives every patch one *cell* of ``T_c x T_c`` texels over that
square (``T_c = cell_c``, the manifest's ``tiles.texture.levels[c].cell``), in the single
patch's texel rule (:class:`client_py.layers.TextureImage`: texel ``(x, y)``, ``y = 0`` the
top row, is centred at ``u = (x + 1/2) / T``, ``v = 1 - (y + 1/2) / T``). One file per
patch would cost a visitor hundreds of requests, so the cells of a run of consecutive
patches (whole detail groups, Morton-ordered: a compact piece of the object) travel in one
image, ``texture/C/G.webp`` (:func:`colour_pack_name`, ``G`` the pack's first detail
group). The cells sit in *blocks* of ``b x b`` cells (``b``, the level's ``block``, a power
of two; 1 in bundles written before it): slot ``s = patch - first`` is in block
``s div b^2``, the blocks laid in rows of ``ceil(sqrt(blocks))`` from the top, and inside
its block at the Morton (Z-order) position of ``s mod b^2`` (:func:`cell_origin`,
:func:`pack_shape`); cells past the last patch are filler. With ``b = 1`` this is a row of
``ceil(sqrt(count))`` cells after another. The fitter makes a block one WebP macroblock
(16 texels) wide, so each macroblock holds consecutive, neighbouring patches (the order is
a k-d tree's): cells of 4 texels in rows put patches a row apart on the object in one
macroblock, and on the Bali mask took 11 % more bytes for 24 % more texel error.

The mesh is coloured per vertex, as a single patch's level PLY is
(``client_py.layers.vertex_colours``): a vertex of :class:`~client_py.atlas_mesh.AtlasMesh`
has the ``(u, v)`` of the patch that owns it (``patches``), and takes the bilinear sample of
that patch's cell (clamped to the cell's own texels, so no neighbour's colour bleeds in),
at the colour level of the patch's group. Per-vertex colour keeps the welded mesh welded
(a border vertex has one colour, as it has one position), is what 3DHOP's PLY loader
reads, and costs the viewer no texture binding per patch; level ``c``'s cells have as
many texels per side as the level's mesh has cells per patch side, so the vertices show
what the texels hold. (client_py decodes no images: the browser or Pillow does.)
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from .layers import MAX_LEVEL, TextureImage

#: the extension of an atlas's colour images
COLOUR_PACK_EXTENSION = "webp"
#: ``tiles.texture.format`` of packs whose cells lie in rows (every level's ``block`` 1), and
#: of packs laid in blocks: a reader from before blocks accepts only the first, so it refuses
#: a bundle whose cells it would read from the wrong places
ROWS_FORMAT, BLOCKS_FORMAT = "webp", "webp-blocks"
#: texels per side of the largest cell (a level's cells are at most this wide)
MAX_CELL = 1024
#: cells per side of the largest block of a pack's layout (:func:`cell_origin`)
MAX_BLOCK = 64
#: texels per side of the largest image of a pack (WebP's limit is 16383)
MAX_PACK_SIDE = 16383


def colour_pack_name(level: int, group: int) -> str:
    """The bundle file of level ``level``'s colour cells starting at detail group ``group``."""
    for name, value in (("level", level), ("group", group)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
    return f"texture/{level}/{group}.{COLOUR_PACK_EXTENSION}"


def colour_pack_name_parts(name: str) -> tuple[int, int] | None:
    """``(C, G)`` of a colour pack name ``texture/C/G.webp`` (:func:`colour_pack_name`),
    or ``None``."""
    parts = name.split("/")
    suffix = "." + COLOUR_PACK_EXTENSION
    if len(parts) != 3 or parts[0] != "texture" or not parts[2].endswith(suffix):
        return None
    numbers = (parts[1], parts[2][: -len(suffix)])
    if not all(x.isdigit() and x.isascii() and (x == "0" or x[0] != "0") for x in numbers):
        return None
    return int(numbers[0]), int(numbers[1])


def pack_columns(count: int) -> int:
    """Cell columns of a pack of ``count`` patches: ``ceil(sqrt(count))`` (a near-square
    image: the fewest filler cells for a square-ish layout)."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"count must be an integer >= 1, got {count!r}")
    return math.isqrt(count - 1) + 1


def check_block(block: object) -> int:
    """``block`` if it is a power of two in ``1..MAX_BLOCK`` (cells per block side), else
    ``ValueError``."""
    if isinstance(block, bool) or not isinstance(block, int) or not 1 <= block <= MAX_BLOCK \
            or block & (block - 1):
        raise ValueError(f"block must be a power of two in 1..{MAX_BLOCK}, got {block!r}")
    return block


def _block_count(count: int, block: int) -> int:
    pack_columns(count)  # checks count
    return -(-count // (check_block(block) ** 2))


def texture_format(blocks: Sequence[int]) -> str:
    """``tiles.texture.format`` of colour levels laid in blocks of ``blocks[c]`` cells a
    side: :data:`ROWS_FORMAT` when every block is 1, else :data:`BLOCKS_FORMAT`."""
    return ROWS_FORMAT if all(check_block(b) == 1 for b in blocks) else BLOCKS_FORMAT


def pack_shape(count: int, cell: int, block: int = 1) -> tuple[int, int]:
    """``(width, height)`` in texels of a pack of ``count`` cells of ``cell`` texels, in
    blocks of ``block x block`` cells: rows of ``pack_columns(blocks)`` blocks."""
    blocks = _block_count(count, block)
    columns = pack_columns(blocks)
    side = block * cell
    return columns * side, -(-blocks // columns) * side


def cell_origin(slot: int, count: int, cell: int, block: int = 1) -> tuple[int, int]:
    """``(x, y)`` of the top-left texel of cell ``slot`` (``0..count - 1``) in its pack of
    ``block x block`` cell blocks: block ``slot div block^2`` in the rows of blocks, then the
    Morton position of ``slot mod block^2`` in it (x from the even bits, y from the odd)."""
    columns = pack_columns(_block_count(count, block))
    b, k = divmod(slot, block * block)
    x = y = 0
    for bit in range(block.bit_length() - 1):
        x |= (k >> (2 * bit) & 1) << bit
        y |= (k >> (2 * bit + 1) & 1) << bit
    return ((b % columns) * block + x) * cell, ((b // columns) * block + y) * cell


def colour_level(detail_level: int, levels: int) -> int:
    """The colour level drawn with a group at detail level ``detail_level`` (``-1``: the
    base): ``min(max(detail_level, 0), levels - 1)`` — level ``c``'s cells match level
    ``c``'s mesh, and the base shows level 0."""
    return min(max(detail_level, 0), levels - 1)


@dataclass(frozen=True)
class ColourPack:
    """A decoded colour image: the cells of patches ``first .. first + count - 1`` at
    colour level ``level``, ``cell`` texels per side each, in blocks of ``block x block``
    cells (:func:`cell_origin`), ``rgb`` the ``width x height`` image's bytes (3 per texel,
    rows top to bottom)."""

    level: int
    first: int
    count: int
    cell: int
    width: int
    height: int
    rgb: bytes
    block: int = 1

    def __post_init__(self) -> None:
        for name, value, lo, hi in (("level", self.level, 0, MAX_LEVEL),
                                    ("first", self.first, 0, 1 << 20),
                                    ("count", self.count, 1, 1 << 20),
                                    ("cell", self.cell, 1, MAX_CELL)):
            if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
                raise ValueError(f"{name} must be an integer in {lo}..{hi}, got {value!r}")
        expected = pack_shape(self.count, self.cell, self.block)
        if (self.width, self.height) != expected:
            raise ValueError(f"a colour pack of {self.count} cells of {self.cell} texels in "
                             f"blocks of {self.block} is {expected[0]}x{expected[1]}, got "
                             f"{self.width}x{self.height}")
        if len(self.rgb) != 3 * self.width * self.height:
            raise ValueError(f"rgb has {len(self.rgb)} bytes; a {self.width}x{self.height} "
                             f"RGB image needs {3 * self.width * self.height}")

    def origin(self, patch: int) -> tuple[int, int]:
        """``(x, y)`` of the top-left texel of ``patch``'s cell in the image."""
        return cell_origin(patch - self.first, self.count, self.cell, self.block)

    def cell_image(self, patch: int) -> TextureImage:
        """Patch ``patch``'s cell as a :class:`~client_py.layers.TextureImage` over its whole
        ``[0, 1]^2`` (node ``0/0_0``): the single patch's sampling rule."""
        if not self.first <= patch < self.first + self.count:
            raise ValueError(f"patch {patch} is not in this pack's patches {self.first}.."
                             f"{self.first + self.count - 1}")
        x, y = self.origin(patch)
        row, size = 3 * self.width, 3 * self.cell
        rgb = b"".join(self.rgb[(y + r) * row + 3 * x:(y + r) * row + 3 * x + size]
                       for r in range(self.cell))
        return TextureImage(0, 0, 0, self.cell, self.cell, rgb)


def atlas_vertex_colours(patches: Sequence[int], uvs: Sequence[float],
                         colour_of_patch: Mapping[int, ColourPack]) -> array:
    """RGB per vertex (``array('B')``): vertex ``k`` of patch ``patches[k]`` at ``(u, v) =
    uvs[2k : 2k + 2]`` takes the bilinear sample of that patch's cell in
    ``colour_of_patch[patch]``; ``0, 0, 0`` for a patch with no pack.

    ``patches`` and ``uvs`` are an :class:`~client_py.atlas_mesh.AtlasMesh`'s ``patches``
    and ``uvs``. The sample is :meth:`~client_py.layers.TextureImage.sample` of the cell
    (:meth:`ColourPack.cell_image`), the same float operations read in place from the pack
    (tests/test_atlas_texture.py holds them equal): a pure-Python loop of a few operations
    per vertex, for the viewer's worker without numpy.
    """
    n = len(patches)
    if len(uvs) != 2 * n:
        raise ValueError(f"uvs has {len(uvs)} values; {n} vertices need {2 * n}")
    out = bytearray(3 * n)
    where: dict[int, tuple | None] = {}
    # (u, v, cell, image row) -> the four texels' offsets from the cell's first byte and
    # the weights: the mesh's vertices sit at a few grid parameters, so these come once
    sampling: dict[tuple, tuple] = {}
    for m, f, u, v in zip(range(0, 3 * n, 3), patches, uvs[0::2], uvs[1::2], strict=True):
        cell = where.get(f, False)
        if cell is False:
            pack = colour_of_patch.get(f)
            if pack is None:
                cell = where[f] = None
            else:
                x, y = pack.origin(f)
                row = 3 * pack.width
                cell = where[f] = (pack.rgb, row, y * row + 3 * x, pack.cell)
        if cell is None:
            continue
        rgb, row, first, t = cell
        key = (u, v, t, row)
        at = sampling.get(key)
        if at is None:
            at = sampling[key] = _bilinear_taps(u, v, t, row)
        o00, o01, o10, o11, gx, fx, gy, fy = at
        p00, p01, p10, p11 = first + o00, first + o01, first + o10, first + o11
        out[m] = int((rgb[p00] * gx + rgb[p01] * fx) * gy
                     + (rgb[p10] * gx + rgb[p11] * fx) * fy + 0.5)
        out[m + 1] = int((rgb[p00 + 1] * gx + rgb[p01 + 1] * fx) * gy
                         + (rgb[p10 + 1] * gx + rgb[p11 + 1] * fx) * fy + 0.5)
        out[m + 2] = int((rgb[p00 + 2] * gx + rgb[p01 + 2] * fx) * gy
                         + (rgb[p10 + 2] * gx + rgb[p11 + 2] * fx) * fy + 0.5)
    return array("B", out)


def _bilinear_taps(u: float, v: float, t: int, row: int) -> tuple:
    """The bilinear sample at ``(u, v)`` of a ``t x t`` cell in an image of ``row`` bytes a
    row (:func:`atlas_vertex_colours`): the byte offsets of texels ``(x0, y0), (x1, y0),
    (x0, y1), (x1, y1)`` from the cell's first byte and the weights ``1 - fx, fx, 1 - fy,
    fy``, with ``x = u t - 1/2``, ``y = (1 - v) t - 1/2`` clamped to ``[0, t - 1]`` (image
    rows run down in ``v``), ``x0 = min(int(x), t - 2)`` (``0`` for one texel), ``x1 = x0 +
    1``, ``fx = x - x0`` (``y`` likewise)."""
    x = u * t - 0.5
    y = (1.0 - v) * t - 0.5
    last = t - 1.0
    x = 0.0 if x < 0.0 else (last if x > last else x)
    y = 0.0 if y < 0.0 else (last if y > last else y)
    if t > 1:
        x0, y0 = min(int(x), t - 2), min(int(y), t - 2)
        x1, y1 = x0 + 1, y0 + 1
    else:
        x0 = y0 = x1 = y1 = 0
    fx, fy = x - x0, y - y0
    return (y0 * row + 3 * x0, y0 * row + 3 * x1, y1 * row + 3 * x0, y1 * row + 3 * x1,
            1 - fx, fx, 1 - fy, fy)


def colours_by_patch(packs: Sequence[ColourPack], patches: int) -> dict[int, ColourPack]:
    """``{patch: pack}`` of packs of ONE colour level (a level plan's) that hold each of
    ``patches`` patches' cell exactly once.

    Raises
    ------
    ValueError
        Packs of several levels, a patch in two packs, or a patch in none.
    """
    out: dict[int, ColourPack] = {}
    for pack in packs:
        if not isinstance(pack, ColourPack):
            raise ValueError(f"packs must be ColourPack objects, got {type(pack).__name__}")
        if pack.level != packs[0].level:
            raise ValueError(f"colour packs of levels {packs[0].level} and {pack.level} were "
                             "given; a level's plan names packs of one colour level")
        for f in range(pack.first, pack.first + pack.count):
            if f in out:
                raise ValueError(f"patch {f} is in two colour packs")
            out[f] = pack
    missing = [f for f in range(patches) if f not in out]
    if missing:
        raise ValueError(f"no colour pack holds patch {missing[0]} ({len(missing)} of "
                         f"{patches} patches lack one); give the packs the plan names")
    return out


def colours_for_groups(packs: Sequence[ColourPack], groups: Sequence[tuple[int, int]],
                       levels: Sequence[int], colour_levels: int) -> dict[int, ColourPack]:
    """``{patch: pack}``: for group ``g`` (patches ``first, count`` = ``groups[g]``) drawn
    at detail level ``levels[g]``, the pack of colour level :func:`colour_level` that holds
    its patches; patches no given pack holds are left out (drawn black).

    Raises
    ------
    ValueError
        ``levels`` not one per group.
    """
    if len(levels) != len(groups):
        raise ValueError(f"levels has {len(levels)} values; there are {len(groups)} groups")
    by_level: dict[int, list[ColourPack]] = {}
    for pack in packs:
        if not isinstance(pack, ColourPack):
            raise ValueError(f"packs must be ColourPack objects, got {type(pack).__name__}")
        by_level.setdefault(pack.level, []).append(pack)
    out: dict[int, ColourPack] = {}
    for (first, count), level in zip(groups, levels, strict=True):
        c = colour_level(level, colour_levels)
        for pack in by_level.get(c, ()):
            if pack.first <= first and first + count <= pack.first + pack.count:
                for f in range(first, first + count):
                    out[f] = pack
                break
    return out


def error_colour_pack(codes: bytes, patches: int, side: int, palette: bytes) -> ColourPack:
    """The atlas's error map as one colour pack of every patch, for
    :func:`atlas_vertex_colours` (the one per-vertex colouring rule of an atlas).

    ``codes`` are the error raster's one-byte codes (docs/format.md, "error_raster" of an
    atlas: patch after patch, ``side x side`` cells each, row ``i`` over ``u``, column ``j``
    over ``v``), ``palette`` the ``3 x 256`` RGB bytes of each code (the viewer's colour scale
    and its colour of no scan point, ``web/src/error-map.js``, so the scale is defined once).
    Cell ``(i, j)`` of patch ``f`` is texel ``(x, y) = (i, side - 1 - j)`` of the patch's cell
    (the texel rule above); a vertex then takes the bilinear blend of the cell colours
    around it, as the single patch's map interpolates its cells.

    Raises
    ------
    ValueError
        ``codes`` or ``palette`` of the wrong length, or a bad count or side.
    """
    codes, palette = bytes(codes), bytes(palette)
    if len(palette) != 3 * 256:
        raise ValueError(f"palette has {len(palette)} bytes; 256 RGB colours need 768")
    if isinstance(side, bool) or not isinstance(side, int) or not 1 <= side <= MAX_CELL:
        raise ValueError(f"side must be an integer in 1..{MAX_CELL}, got {side!r}")
    if isinstance(patches, bool) or not isinstance(patches, int) or patches < 1:
        raise ValueError(f"patches must be an integer >= 1, got {patches!r}")
    if len(codes) != patches * side * side:
        raise ValueError(f"the error raster has {len(codes)} codes; {patches} patches of "
                         f"{side}x{side} cells need {patches * side * side}")
    width, height = pack_shape(patches, side)
    rgb = bytearray(3 * width * height)
    for f in range(patches):
        left, top = cell_origin(f, patches, side)
        for i in range(side):
            for j in range(side):
                code = codes[(f * side + i) * side + j]
                at = 3 * ((top + side - 1 - j) * width + left + i)
                rgb[at:at + 3] = palette[3 * code:3 * code + 3]
    return ColourPack(0, 0, patches, side, width, height, bytes(rgb))
