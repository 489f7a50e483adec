"""The memory budget of a fit: its two largest linear systems, estimated before they are built.

A fit's peak memory is set by one of two solves, each freed before the next begins:

* the base patch (``fitter.fitting.fit``): normal equations over the ``n = n_u n_v``
  control points, solved by banded Cholesky with a band of ``b = r n_v + r`` unknowns,
  ``r = max(p, 2)`` (the basis couples control points ``p`` apart, the thin-plate term 2
  apart), from a collocation matrix of ``m`` rows with ``(p + 1)^2`` non-zeros each:

      B_base(n_u, n_v, p, m) = 12 (b + 1) n + 64 (p + 1)^2 m    bytes

  (the band array and LAPACK's copy of it, and the rows with their sparse copies);
* a detail level (``fitter.fitting.detail.fit_level``): a sparse solve (SuperLU as a
  Cholesky factorisation, ``fitter.fitting.spd.spd_lu``) over the ``n^2`` coefficients
  of the level's ``n x n`` grid, ``n = s 2^k + p``:

      B_detail(k, s) = 7168 n^2    bytes.

The budget bounds what the *options* scale: the grid, the degree, the sample the base is
fitted to (``samples``), the detail levels and spans. What scales with the scan alone
(about 280 bytes a point for a level's collocation rows, and the points themselves) is
bounded by the input limit ``max_points`` (``fitter.fitting.io.limits``) instead, so a
large scan keeps its detail levels.

Both constants were measured (peak RSS, ``resource.getrusage``, numpy 2.4 / scipy 1.17):
the base at grids 64..384 with 6 x 10^4 and 6 x 10^5 rows (the formula over-states by
up to 30 %), the detail levels at ``n = 66..514`` with 4 x 10^4 and 3 x 10^5 points
(6.2-7.0 KiB a coefficient: SuperLU's fill grows about linearly on these grids; measured
with partial pivoting, which the solve no longer does: the same order and fill, so an upper
bound). A level
of ``n = 514``
(16 spans, level 5) needs 1.8 GB; ``--detail-levels 8 --detail-spans 64`` asks for
``n = 8194``, 481 GB — the solve that a memory cap turns into a segfault inside SuperLU.

:func:`plan_memory` compares each with the budget (default :data:`DEFAULT_MEMORY_BUDGET`,
2 GiB; ``fit_scan(memory_budget=)``, ``tessera fit --memory-budget``): a grid or an
explicit ``detail_levels`` over it is refused with an ``OptionError`` naming the options,
the estimate and what would fit; the automatic depth is capped at the levels that fit,
and the manifest's ``memory`` records it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from .options import OptionError

DEFAULT_MEMORY_BUDGET = 2 << 30
BASE_BYTES_PER_BAND_ENTRY = 12
BASE_BYTES_PER_ROW_NONZERO = 64
DETAIL_BYTES_PER_COEFFICIENT = 7168


def _gib(nbytes: float) -> str:
    return f"{nbytes / (1 << 30):.2f} GiB"


def base_fit_bytes(grid: tuple[int, int], degree: int, rows: int) -> int:
    """``B_base``: bytes of the base patch's solve on a ``grid (n_u, n_v)`` of degree
    ``degree`` with ``rows`` data rows (module docstring)."""
    n_u, n_v = grid
    reach = max(degree, 2)
    band = reach * n_v + reach
    return (BASE_BYTES_PER_BAND_ENTRY * (band + 1) * n_u * n_v
            + BASE_BYTES_PER_ROW_NONZERO * (degree + 1) ** 2 * rows)


def detail_level_bytes(level: int, spans: int, degree: int) -> int:
    """``B_detail``: bytes of the solve of detail level ``level`` with ``spans`` spans per
    tile side and fields of degree ``degree`` (module docstring)."""
    n = (spans << level) + degree
    return DETAIL_BYTES_PER_COEFFICIENT * n * n


@dataclass
class MemoryPlan:
    """What a fit will solve within ``budget`` bytes: the base's estimate (of its largest
    grid), the detail levels and the estimate of the finest, and the automatic depth
    before the budget capped it (``None`` when it did not, or the depth was explicit)."""

    budget: int
    base_bytes: int
    detail_levels: int
    detail_bytes: int
    detail_levels_uncapped: int | None = None

    def manifest(self) -> dict:
        """The manifest's ``memory`` entry."""
        return asdict(self)


def plan_memory(largest_grid: tuple[int, int], degree: int, base_rows: int,
                detail_levels: int | None, auto_levels: int, detail_spans: int,
                detail_degree: int, budget: int = DEFAULT_MEMORY_BUDGET) -> MemoryPlan:
    """Check a fit's two systems against ``budget`` bytes (module docstring).

    Parameters
    ----------
    largest_grid : (n_u, n_v)
        The largest control grid the fit may try (``grid``, or what ``max_error`` grows to).
    degree : int
        The base's degree ``p``.
    base_rows : int
        Data rows of the base solve (the fitted sample, at most the points).
    detail_levels : int or None
        The option as given (``None``: automatic, ``auto_levels`` deep).
    auto_levels : int
        The automatic depth (``fitter.fitting.detail.auto_levels``).
    detail_spans, detail_degree : int
        Spans per detail tile side and the detail fields' degree.
    budget : int
        Bytes, ``>= 1``.

    Raises
    ------
    ValueError
        ``budget`` not a positive integer.
    OptionError
        The base's estimate over ``budget`` (naming ``grid``/``max_grid``), or an explicit
        ``detail_levels`` whose finest level's estimate is over it (naming
        ``detail_levels`` and ``detail_spans``), each with the estimate and what fits.
    """
    if isinstance(budget, bool) or not isinstance(budget, int) or budget < 1:
        raise ValueError(f"memory_budget must be a positive number of bytes, got {budget!r}")
    base = base_fit_bytes(largest_grid, degree, base_rows)
    if base > budget:
        side = max(largest_grid)
        while side > degree + 1 and base_fit_bytes((side, side), degree, base_rows) > budget:
            side -= 1
        raise OptionError(
            f"grid {largest_grid[0]}x{largest_grid[1]} (degree {degree}, the largest grid "
            f"this fit may try: grid, or max_grid with max_error) needs about {_gib(base)} "
            f"for its solve, over the memory budget of {_gib(budget)}; a grid of at most "
            f"{side}x{side} fits (or raise the budget: --memory-budget, "
            "fit_scan(memory_budget=))")

    def finest(levels: int) -> int:
        return 0 if levels == 0 else detail_level_bytes(levels - 1, detail_spans,
                                                        detail_degree)

    if detail_levels is not None:
        if finest(detail_levels) > budget:
            most = _levels_within(detail_spans, detail_degree, budget, detail_levels)
            side = (detail_spans << (detail_levels - 1)) + detail_degree
            raise OptionError(
                f"detail_levels {detail_levels} with detail_spans {detail_spans}: level "
                f"{detail_levels - 1} solves for {side:,}^2 "
                f"coefficients, about {_gib(finest(detail_levels))}, over the memory budget "
                f"of {_gib(budget)}; at most {most} levels fit at {detail_spans} spans (or "
                "raise the budget: --memory-budget, fit_scan(memory_budget=))")
        return MemoryPlan(budget, base, detail_levels, finest(detail_levels))
    levels = _levels_within(detail_spans, detail_degree, budget, auto_levels)
    return MemoryPlan(budget, base, levels, finest(levels),
                      auto_levels if levels < auto_levels else None)


def _levels_within(spans: int, degree: int, budget: int, wanted: int) -> int:
    """The most levels ``<= wanted`` whose finest solve fits ``budget``."""
    levels = 0
    while levels < wanted and detail_level_bytes(levels, spans, degree) <= budget:
        levels += 1
    return levels
