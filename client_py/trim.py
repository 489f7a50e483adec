"""Trim mask: which part of a patch's rectangular parameter domain the object covers.

A scan projected to the rectangle ``[u_a, u_b] x [v_a, v_b]`` rarely fills it
(the paper's Fig. 6: a non-rectangular patch). The mask is a ``rows x cols``
grid of booleans over the domain, row ``r`` covering ``u`` in
``[u_a + r du, u_a + (r + 1) du)`` and column ``c`` the same in ``v``; a
tessellation leaves out the cells whose centre falls in an uncovered mask cell.
"""

from __future__ import annotations

from collections.abc import Sequence

MAX_SIDE = 1024  # cells per side: finer than any tessellation a browser draws


class TrimMask:
    """Boolean coverage grid over the parameter domain.

    Parameters
    ----------
    cells : sequence of sequences of bool, shape ``(rows, cols)``
        ``cells[r][c]`` is true where the object covers that part of the domain.
    """

    __slots__ = ("rows", "cols", "_cells")

    def __init__(self, cells: Sequence[Sequence[object]]) -> None:
        if hasattr(cells, "tolist"):
            cells = cells.tolist()
        rows = len(cells)
        cols = len(cells[0]) if rows else 0
        if rows < 1 or cols < 1:
            raise ValueError(f"trim mask must have at least 1x1 cells, got {rows}x{cols}")
        if rows > MAX_SIDE or cols > MAX_SIDE:
            raise ValueError(f"trim mask of {rows}x{cols} cells exceeds {MAX_SIDE} per side")
        flat = bytearray()
        for r, row in enumerate(cells):
            if len(row) != cols:
                raise ValueError(f"trim mask row {r} has {len(row)} cells, row 0 has {cols}")
            flat.extend(1 if cell else 0 for cell in row)
        self.rows = rows
        self.cols = cols
        self._cells = bytes(flat)

    @classmethod
    def from_flat(cls, rows: int, cols: int, flat: bytes) -> TrimMask:
        """Build from ``rows * cols`` bytes, 0 or 1, row-major (no copy of rows)."""
        if not (1 <= rows <= MAX_SIDE and 1 <= cols <= MAX_SIDE):
            raise ValueError(f"trim mask of {rows}x{cols} cells: 1..{MAX_SIDE} per side accepted")
        if len(flat) != rows * cols:
            raise ValueError(f"trim mask needs {rows * cols} cells, got {len(flat)}")
        mask = cls.__new__(cls)
        mask.rows, mask.cols, mask._cells = rows, cols, bytes(1 if b else 0 for b in flat)
        return mask

    @property
    def flat(self) -> bytes:
        """Cells as ``rows * cols`` bytes (0 or 1), row-major."""
        return self._cells

    def covered_fraction(self) -> float:
        return sum(self._cells) / len(self._cells)

    def covers(self, s: float, t: float) -> bool:
        """Coverage at normalised domain coordinates ``s, t`` in ``[0, 1]``."""
        r = min(int(s * self.rows), self.rows - 1)
        c = min(int(t * self.cols), self.cols - 1)
        return bool(self._cells[max(r, 0) * self.cols + max(c, 0)])

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, TrimMask)
            and (self.rows, self.cols, self._cells) == (other.rows, other.cols, other._cells)
        )

    def __repr__(self) -> str:
        return f"TrimMask({self.rows}x{self.cols}, covered={self.covered_fraction():.3f})"
