"""Code a control mesh's triangles by a gate traversal: ``.tsa`` version 6's connectivity.

The triangles are grown from a first one, a piece at a time, across *gates*: the edges
``(x, y)`` of coded triangles whose twin ``(y, x)`` no coded triangle runs yet. A stack
holds the gates; a popped gate that a later triangle has closed costs nothing, else one
bit says whether it is a border, and if not, the triangle ``(y, x, c)`` across it is coded
by its far corner ``c`` alone: a point not used before (Edgebreaker's ``C``), the head of
an open edge ``(y, c)`` (``R``, or ``E`` when it closes both sides), the tail of an open
edge ``(c, x)`` (``L``), or else (``S``, a handle, a point shared by pieces) the distance
back to its number. This is Edgebreaker's traversal and symbols (Rossignac, *Edgebreaker:
connectivity compression for triangle meshes*, IEEE TVCG 5(1), 1999), decoded in one
forward pass as the cut-border machine does (Gumhold & Straßer, *Real time compression of
triangle mesh connectivity*, SIGGRAPH 1998), the region's boundary kept as open edges per
point, instead of Wrap&Zip's (Rossignac & Szymczak 1999) or *Spirale Reversi*'s (Isenburg
& Snoeyink 2000) second pass: ``S`` carries its point's offset, so borders (holes),
handles and several pieces need no special symbols. Each decision is an adaptive binary
range-coded bit (:mod:`client_py.rangecoder`) in the context of the symbol before it and
of the triangles decoded around the gate's ends.

A piece's first triangle ``(p, q, r)`` pushes all three of its edges, ``(p, q)``, ``(r,
p)``, ``(q, r)`` (``(q, r)`` popped first), as Edgebreaker's first triangle opens its
whole boundary; each further triangle ``(y, x, c)`` pushes ``(c, y)`` and ``(x, c)``, its
third edge being the gate it came across. A piece ends when the stack is empty, and the
next starts at the first given triangle not yet coded. The triangles are listed in the
order coded, each from the gate's far end ``(y, x, c)`` (a piece's first as it was given),
and the points numbered in the order the triangles first use them (points in no triangle
last, in their own order): for triangles in any order, that is
``client_py.control_mesh.traversal_order`` of them numbered by ``canonical_control_mesh``,
the order version 5 codes (``tests/test_control_mesh.py`` checks it on shuffled and
rotated triangles, a piece's first a bridge). On the fitted bases of sessions 30-31 (8,000
triangles) the triangles took 1.3-1.8 bits each, 2.1 on Buddha scan 0's ragged rim,
against 3.3-3.9 in version 5's coder.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import islice

from .errors import PatchFormatError
from .rangecoder import HALF, RangeDecoder, RangeEncoder, decode_exp_golomb, encode_exp_golomb

#: ``c`` is ranked among at most this many open edges at ``y`` (or ``x``); beyond, it is
#: coded by its distance (real control meshes have one or two)
RANK_LIMIT = 4
#: the Exp-Golomb prefix of a distance back is at most ``DISTANCE_BITS - 1`` ones: ``d`` up
#: to ``2^18 - 1``, beyond the ``2^17`` points a file may hold
DISTANCE_BITS = 18
#: the symbols, each the context of the next: a piece's start, new point, next, previous,
#: other
START, NEW, NEXT, PREVIOUS, OTHER = range(5)


class _TriangleModel:
    """Adaptive contexts, each also by the symbol before (5): the border bit by whether the
    gate before was a border and whether ``x`` ends and ``y`` starts a border edge (8); the
    new-point bit by the coded triangles at ``x`` and at ``y`` (each up to 7: 64); the next
    (previous) hit by those at ``y`` (``x``) and whether the other pool is empty (16); a
    rank's unary bits, at most ``RANK_LIMIT - 1`` (the last rank needs no stop bit), next's
    then previous's; a distance's Exp-Golomb prefix and suffix; a piece's first corners by
    slot."""

    def __init__(self) -> None:
        self.border = [HALF] * 40
        self.new = [HALF] * 5 * 64
        self.next = [HALF] * 5 * 16
        self.previous = [HALF] * 5 * 16
        self.rank = [HALF] * (2 * (RANK_LIMIT - 1))
        self.first = [HALF] * 3
        self.prefix = [HALF] * DISTANCE_BITS
        self.suffix = [HALF] * DISTANCE_BITS


def encode_triangles(enc: RangeEncoder, n_points: int, triangles: Sequence[Sequence[int]]
                     ) -> tuple[list[int], list[tuple[int, int, int]]]:
    """Code ``triangles (T, 3)``, a checked oriented 2-manifold over ``n_points``, in any
    numbering and order. Returns the file's ``order`` (point ``order[k]`` becomes ``k``)
    and the triangles as :func:`decode_triangles` gives them back (the module docstring)."""
    return _code(enc, len(triangles), n_points, [tuple(t) for t in triangles], 0)


def decode_triangles(dec: RangeDecoder, n_tris: int, n_points: int, start: int
                     ) -> list[tuple[int, int, int]]:
    """Inverse of :func:`encode_triangles`: ``n_tris`` triangles over ``n_points``.

    Raises
    ------
    PatchFormatError
        (at ``start``, the coded stream's offset) a point beyond ``n_points``, a distance
        beyond the points so far, a triangle with a repeated corner or that runs a directed
        edge a coded triangle runs.
    """
    return _code(dec, n_tris, n_points, None, start)[1]


def _code(coder: RangeEncoder | RangeDecoder, n_tris: int, n: int,
          given: list[tuple[int, ...]] | None, start: int
          ) -> tuple[list[int] | None, list[tuple[int, int, int]]]:
    """Both directions of the traversal (``given`` the triangles to encode, or ``None``).
    The encoder keys its state by the given points, the decoder by the file's numbers;
    both make the same calls in the same order, so their lists keep the same order. Returns
    the encoder's ``order`` (``None`` when decoding) and the triangles."""
    encoding = given is not None
    model = _TriangleModel()
    if encoding:
        across = {}  # the directed edge a n + b: the far corner of its triangle
        for a, b, c in given:
            across[a * n + b], across[b * n + c], across[c * n + a] = c, a, b
        number = [-1] * n  # a given point's file number
        order: list[int] = []
        put, get = coder.bit, None
    else:
        across, number, order, put, get = None, None, None, None, coder.bit
    run: set[int] = set()  # the directed edges a n + b of the coded triangles
    ends: set[int] = set()  # the gates found to be borders
    # per x the open edges' heads (x, y), per y their tails, in the order opened: dicts,
    # so that a point of any valence (a hostile file's) costs a bounded time per edge; the
    # decoder's points are numbered as first used, and get theirs then (a hostile header's
    # 2^17 points cost no 2^18 dicts up front)
    heads: list[dict[int, None]] = [{} for _ in range(n)] if encoding else []
    tails: list[dict[int, None]] = [{} for _ in range(n)] if encoding else []
    border_in = [False] * n  # a point ends a border edge
    border_out = [False] * n  # a point starts one
    fans = [0] * n  # per point its coded triangles
    was_border = False
    out: list[tuple[int, int, int]] = []
    used = 0
    next_start = 0  # the encoder's next candidate for a piece's first triangle
    stack: list[tuple[int, int]] = []
    symbol = START

    def fail(reason: str) -> PatchFormatError:
        return PatchFormatError(start, f"triangle {len(out)}: {reason}")

    def add(p: int, q: int, r: int) -> None:
        # the triangle's edges: each new to the coded ones, closing its twin or opening
        for a, b in ((p, q), (q, r), (r, p)):
            key = a * n + b
            if key in run:
                raise fail(f"the edge {a} -> {b} is run twice")
            run.add(key)
            if b * n + a in run:
                if b * n + a in ends:
                    raise fail(f"the edge {a} -> {b} crosses a border")
                del heads[b][a], tails[a][b]
            else:
                heads[a][b] = tails[b][a] = None
        fans[p] += 1
        fans[q] += 1
        fans[r] += 1
        # (q, r) popped next, then (r, p): the traversal turns as Edgebreaker's does (a
        # piece's first also pushes (p, q), beneath them)
        stack.append((r, p))
        stack.append((q, r))

    def point_back() -> int:
        # a corner coded as the distance back from the next new point's number
        d = decode_exp_golomb(coder, model.prefix, 0, model.suffix, 0, DISTANCE_BITS)
        if d is None or d > used:
            raise fail("a corner before the first point")
        return used - d

    def file_number(v: int) -> int:
        if number[v] < 0:
            number[v] = len(order)
            order.append(v)
        return number[v]

    while len(out) < n_tris:
        # a piece's first triangle: each corner new or a distance back
        if encoding:
            while given[next_start][0] * n + given[next_start][1] in run:
                next_start += 1
            tri = given[next_start]
        corners = []
        for slot in range(3):
            if encoding:
                v = tri[slot]
                fresh = number[v] < 0
                put(model.first, slot, fresh)
                if not fresh:
                    encode_exp_golomb(coder, used - number[v], model.prefix, 0,
                                      model.suffix, 0)
                else:
                    used += 1
                    file_number(v)
            else:
                if get(model.first, slot):
                    if used >= n:
                        raise fail(f"uses more than the {n} points")
                    v = used
                    used += 1
                    heads.append({})
                    tails.append({})
                else:
                    v = point_back()
                if v in corners:
                    raise fail(f"corner {v} twice")
            corners.append(v)
        stack.append((corners[0], corners[1]))  # popped last: the piece's first gate
        add(*corners)
        out.append(tuple(corners))
        symbol = START
        while stack and len(out) < n_tris:  # with all coded, the open gates are borders
            x, y = stack.pop()
            gate = x * n + y
            if y * n + x in run or gate in ends:
                continue  # closed since it was opened, or a border already
            context = 8 * symbol + 4 * was_border + 2 * border_in[x] + border_out[y]
            if encoding:
                c = across.get(y * n + x, -1)
                put(model.border, context, c < 0)
                border = c < 0
            else:
                border = get(model.border, context)
            was_border = border
            if border:
                ends.add(gate)
                del heads[x][y], tails[y][x]
                border_out[x] = border_in[y] = True
                continue
            after = list(islice(heads[y], RANK_LIMIT))
            before = list(islice(tails[x], RANK_LIMIT))
            # a new point?
            if encoding:
                fresh = number[c] < 0
                put(model.new, 64 * symbol + 8 * min(fans[x], 7) + min(fans[y], 7), fresh)
            else:
                fresh = get(model.new, 64 * symbol + 8 * min(fans[x], 7) + min(fans[y], 7))
            if fresh:
                symbol = NEW
                if encoding:
                    file_number(c)
                elif used >= n:
                    raise fail(f"uses more than the {n} points")
                else:
                    c = used
                    heads.append({})
                    tails.append({})
                used += 1
            else:
                last, symbol = symbol, OTHER
                for pool, hit, base, name, other, fan in (
                        (after, model.next, 0, NEXT, before, fans[y]),
                        (before, model.previous, RANK_LIMIT - 1, PREVIOUS, after, fans[x])):
                    if not pool:
                        continue
                    if encoding:
                        found = c in pool
                        put(hit, 16 * last + 2 * min(fan, 7) + bool(other), found)
                    else:
                        found = get(hit, 16 * last + 2 * min(fan, 7) + bool(other))
                    if found:
                        rank, target = 0, pool.index(c) if encoding else -1
                        while rank < len(pool) - 1:
                            if encoding:
                                more = rank < target
                                put(model.rank, base + rank, more)
                            else:
                                more = get(model.rank, base + rank)
                            if not more:
                                break
                            rank += 1
                        c = pool[rank] if not encoding else c
                        symbol = name
                        break
                if symbol == OTHER:
                    if encoding:
                        encode_exp_golomb(coder, used - number[c], model.prefix, 0,
                                          model.suffix, 0)
                    else:
                        c = point_back()
                if not encoding and c in (x, y):
                    raise fail(f"corner {c} twice")
            add(y, x, c)
            out.append((y, x, c))
    if encoding:
        for v in range(n):
            file_number(v)
        out = [(number[a], number[b], number[c]) for a, b, c in out]
        return order, out
    return None, out
