"""The stages of ``fit_scan``, in order, with their share of a fit's time: the one list that
``fit_scan``'s progress reports, the CLI's bars and the admin's job progress read.

No numpy or scipy here: the job runner's progress writer imports it.

A stage's weight ``w_s`` is its share of the whole fit's wall time, so the overall
progress of stage ``s`` at fraction ``f`` in ``[0, 1]`` is

    P(s, f) = sum_{t before s} w_t + w_s f,   with sum_s w_s = 1.

The weights are the mean shares of four timed fits with default options
(``manifest["timings"]``, two runs each of the example relief, 80,000 points without
colour, and ``../shared/data/laurana-bust/laurana.ply``, 25,160 points with colour):

=========  ======================  =======
stage      shares measured         weight
=========  ======================  =======
load       0.001 0.087 0.001 0.092  0.045
project    0.013 0.016 0.012 0.016  0.015
features   0.073 0.069 0.075 0.064  0.070
sections   0.002 0.004 0.002 0.003  0.005
linear     0.004 0.026 0.004 0.022  0.015
refine     0.391 0.205 0.377 0.200  0.295
encode     0.056 0.125 0.053 0.119  0.090
error      0.063 0.088 0.059 0.099  0.075
detail     0.298 0.201 0.318 0.190  0.250
texture    0.000 0.098 0.000 0.104  0.050
report     0.097 0.081 0.099 0.091  0.090
=========  ======================  =======

Methods other than ``tessera`` skip ``features`` (and ``linear`` skips ``refine``): their
bar jumps over those stages, which is honest. With ``max_error`` the stages
``sections`` .. ``error`` repeat for each grid size; a progress display should never
move back (``fitter.collection.jobs`` keeps the best value seen).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Stage:
    """One stage of ``fit_scan``: its ``name`` (as reported to ``progress(name, fraction)``
    and recorded in ``manifest["timings"]``), its share ``weight`` of a fit's time and
    what it does."""

    name: str
    weight: float
    does: str


STAGES: tuple[Stage, ...] = (
    Stage("load", 0.045, "read the scan (fitter.fitting.io) or take an in-memory array"),
    Stage("project", 0.015, "choose the map to [0, 1]^2 and the covered points"),
    Stage("features", 0.070, "local PCA and the feature-adaptive sample (tessera only)"),
    Stage("sections", 0.005, "the paper's section matrix"),
    Stage("linear", 0.015, "the initial B-spline, weights 1, uniform clamped knots"),
    Stage("refine", 0.295, "parameter correction and weights (tessera) or eq. 5 (paper)"),
    Stage("encode", 0.090, "base.tsp written and read back, quantisation bits chosen"),
    Stage("error", 0.075, "foot-point deviation of every scan point"),
    Stage("detail", 0.250, "the residual displacement pyramid"),
    Stage("texture", 0.050, "the colour pyramid (when the scan has colour)"),
    Stage("report", 0.090, "tiles, error.png, error.ply, the detached pieces "
          "(fitter.fitting.pieces) and manifest.json written"),
)

#: the stage names in order
STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)

_START: dict[str, float] = {}
_WEIGHT: dict[str, float] = {s.name: s.weight for s in STAGES}
_done = 0.0
for _stage in STAGES:  # tests/test_options.py checks that the weights sum to 1
    _START[_stage.name] = _done
    _done += _stage.weight


def check_stage(name: str) -> str:
    """``name`` if it is a stage of :data:`STAGES`.

    Raises
    ------
    ValueError
        Any other name, with the accepted ones.
    """
    if name not in _WEIGHT:
        raise ValueError(f"stage must be one of {', '.join(STAGE_NAMES)}, got {name!r}")
    return name


def overall_progress(stage: str, fraction: float) -> float:
    """The whole fit's progress ``P(s, f) = sum_{t before s} w_t + w_s f`` in ``[0, 1]`` for
    stage ``s`` at ``fraction`` ``f`` (clipped to ``[0, 1]``).

    Raises
    ------
    ValueError
        ``stage`` not in :data:`STAGES`.
    """
    check_stage(stage)
    return _START[stage] + _WEIGHT[stage] * min(max(float(fraction), 0.0), 1.0)
