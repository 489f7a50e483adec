"""One table of fit options and one list of stages (fitter.fitting.options, .stages): the CLI,
``FitOptions`` and the admin's upload form share every default and refuse the same values
naming the option; ``fit_scan`` reports only the listed stages, and a job's progress bar
moves through the detail and texture stages."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import fields

import pytest
from werkzeug.datastructures import MultiDict

from fitter.cli import build_parser, main
from fitter.collection.jobs import _ProgressWriter
from fitter.collection.uploads import UploadError
from fitter.fitting.examples import relief_scan
from fitter.fitting.options import (
    MAX_PATCHES,
    OPTION,
    OPTIONS,
    FitOptions,
    fit_options,
    form_fields,
    from_args,
    parse_form,
    stored_options,
    unused_by_atlas,
)
from fitter.fitting.pipeline import _Stages, fit_scan
from fitter.fitting.stages import STAGE_NAMES, STAGES, overall_progress
from fitter.server.admin.service import parse_fit_options

#: the documented defaults (README, docs/admin.md), written out independently of the table
DOCUMENTED_DEFAULTS = {
    "grid": (40, 40), "degree": 2, "method": "tessera", "bits": None, "max_error": None,
    "max_grid": None, "patches": None, "base": "smooth", "projection": "auto", "up": "auto",
    "title": None, "description": None, "units": None,
    "feature_strength": 4.0, "seed": 0,
    "samples": 60_000, "detail_levels": None, "detail_spans": 16, "texture": True,
}


def _cli_options(*argv: str, command: str = "fit") -> FitOptions:
    head = ["fit", "scan.ply", "-o", "out"] if command == "fit" else [
        "fit-collection", "scan.ply", "-o", "out"]
    return from_args(build_parser().parse_args([*head, *argv]))


# ----------------------------------------------------------------------- the table
def test_fit_options_fields_are_the_table_in_its_order():
    assert [f.name for f in fields(FitOptions)] == [o.name for o in OPTIONS]
    assert [o.name for o in OPTIONS] == list(DOCUMENTED_DEFAULTS)


def test_the_table_agrees_with_the_fit_modules_that_need_numpy():
    from client_py.atlas import MAX_ATLAS_QUADS
    from fitter.fitting.atlas.fit import AUTO_MAX_TRIANGLES
    from fitter.fitting.detail import SPANS
    from fitter.fitting.parameterize import KINDS

    assert OPTION["projection"].choices == ("auto", *KINDS)
    assert OPTION["detail_spans"].default == SPANS
    # the most patches: three quads per layout triangle of the largest layout, in a bundle
    assert OPTION["patches"].maximum == MAX_PATCHES == 3 * AUTO_MAX_TRIANGLES <= MAX_ATLAS_QUADS


def test_the_options_an_atlas_does_not_use_are_named_when_set():
    assert unused_by_atlas(FitOptions()) == []
    given = FitOptions(grid=(80, 80), seed=3, detail_spans=8, detail_levels=2, bits=10,
                       patches=300, texture=False, title="x")
    assert unused_by_atlas(given) == ["grid", "seed", "detail_spans"]
    # the form and the command line say so in the option's help
    shown = {f["name"]: f["help"] for f in form_fields()}
    assert shown["grid"].endswith("(a single patch; not an atlas)")
    assert not shown["patches"].endswith("(a single patch; not an atlas)")
    cli_help = build_parser()._subparsers._group_actions[0].choices["fit"].format_help()
    assert " ".join(cli_help.split()).count("(a single patch; not an atlas)") == 10


def test_cli_python_and_form_defaults_are_the_same_for_every_option():
    python = {f.name: getattr(FitOptions(), f.name) for f in fields(FitOptions)}
    assert python == DOCUMENTED_DEFAULTS
    for command in ("fit", "fit-collection"):
        assert stored_options(_cli_options(command=command)) == stored_options(FitOptions())
    # every option is on `tessera fit` and in the form; fit-collection leaves out the
    # per-object ones (a title and a description of one object)
    fit_dests = set(vars(build_parser().parse_args(["fit", "s", "-o", "o"])))
    parser_dests = set(vars(build_parser().parse_args(["fit-collection", "s", "-o", "o"])))
    spelled = {o.name for o in OPTIONS if o.cli} | {o.name for o in OPTIONS if o.form}
    assert spelled == set(DOCUMENTED_DEFAULTS) and spelled <= fit_dests
    assert spelled - parser_dests == {"title", "description"}
    assert parse_form({}) == stored_options(FitOptions())
    # the page's fields as rendered (defaults as text, empty for None) read back as defaults
    shown = {f["name"]: f["value"] for f in form_fields()}
    assert set(shown) == spelled
    assert parse_form(shown) == stored_options(FitOptions())
    assert parse_fit_options(MultiDict(shown)) == stored_options(FitOptions())


def test_stored_options_round_trip_and_unknown_ones_are_refused():
    options = FitOptions(grid=(12, 20), max_error=0.5, max_grid=300, texture=False, title="x")
    stored = stored_options(options)
    assert stored["grid"] == [12, 20]
    assert fit_options(stored) == options
    with pytest.raises(ValueError, match="unknown fit option.s. colour"):
        fit_options({**stored, "colour": "red"})


# ------------------------------------------------------------------------ refusals
#: (option, text typed on the CLI / in the form, the same value in Python)
BAD = [
    ("grid", "2000x40", (2000, 40)),
    ("grid", "1x40", (1, 40)),
    ("grid", "2x40", (2, 40)),  # below degree + 1: the rule joining two options
    ("degree", "0", 0),
    ("degree", "6", 6),
    ("method", "magic", "magic"),
    ("bits", "7", 7),
    ("bits", "25", 25),
    ("max_error", "0", 0.0),
    ("max_error", "-1", -1.0),
    ("max_error", "inf", float("inf")),
    ("max_grid", "1025", 1025),
    ("max_grid", "20", 20),  # below the grid's largest side (40)
    ("patches", "0", 0),
    ("patches", "2", 2),  # 1 is a single patch, an atlas has 3 or more: a rule of its own
    ("patches", "27001", 27_001),  # more than the fitter's largest layout makes
    ("base", "nurbs", "nurbs"),
    ("projection", "torus", "torus"),
    ("feature_strength", "101", 101.0),
    ("feature_strength", "-0.5", -0.5),
    ("feature_strength", "nan", float("nan")),
    ("seed", "-1", -1),
    ("samples", "999", 999),
    ("samples", "10000001", 10_000_001),
    ("detail_levels", "9", 9),
    ("detail_levels", "-1", -1),
    ("detail_spans", "3", 3),
    ("detail_spans", "65", 65),
    ("texture", "maybe", "maybe"),
    ("title", "t" * 201, "t" * 201),
    ("units", "u" * 21, "u" * 21),
]


@pytest.mark.parametrize("name, text, value", BAD)
def test_a_bad_value_is_refused_naming_the_option_by_all_three_entry_points(
        name, text, value, capsys, tmp_path):
    option = OPTION[name]
    # Python
    with pytest.raises(ValueError, match=name):
        FitOptions(**{name: value}).validate()
    # the upload form (the admin pages and API)
    with pytest.raises(UploadError, match=name):
        parse_fit_options(MultiDict({option.form: text}))
    # the command line: exit status 2 and the message
    argv = ["fit", str(tmp_path / "scan.ply"), "-o", str(tmp_path / "out")]
    argv += [option.cli] if option.kind == "bool" else [option.cli, text]
    if option.kind == "bool":
        argv[-1] = f"{option.cli}={text}"  # a flag takes no value: refused by argparse
    try:
        status = main(argv)
    except SystemExit as exc:
        status = exc.code
    err = capsys.readouterr().err
    assert status == 2
    if option.kind == "bool":
        assert option.cli in err
    else:
        assert name in err and text in err, err
    assert not (tmp_path / "out").exists()


def test_a_text_that_is_not_a_number_is_refused_with_the_accepted_range():
    with pytest.raises(UploadError, match=r"degree must be an integer in 1\.\.5, got 'two'"):
        parse_fit_options(MultiDict({"degree": "two"}))
    with pytest.raises(UploadError, match=r"grid must be N or NxM such as 40x40, got '40y40'"):
        parse_fit_options(MultiDict({"grid": "40y40"}))
    with pytest.raises(ValueError, match=r"unknown form field\(s\) colour; accepted: "):
        parse_form({"colour": "red"})


# -------------------------------------------------------------- one max_grid rule
@pytest.mark.parametrize("grid", [(40, 40), (128, 12), (200, 200), (12, 1024)])
def test_one_max_grid_rule_everywhere(grid):
    text = f"{grid[0]}x{grid[1]}"
    cli = _cli_options("--grid", text)  # the CLI refused every grid above 128 before
    form = fit_options(parse_form({"grid": text}))
    python = FitOptions(grid=grid)
    python.validate()
    for options in (cli, form, python):
        assert options.grid == grid and options.max_grid is None
        assert options.largest_grid == max(128, *grid)
    assert _cli_options("--grid", text, "--max-grid", "1024").largest_grid == 1024
    assert fit_options(parse_form({"grid": text, "max_grid": "1024"})).largest_grid == 1024


def test_the_form_reads_the_new_fields():
    stored = parse_form({"detail_levels": "3", "detail_spans": "24", "texture": "no",
                         "max_grid": "256", "samples": "20000", "feature_strength": "0",
                         "seed": "7", "max_error": "0.25", "bits": "12"})
    assert (stored["detail_levels"], stored["detail_spans"], stored["texture"]) == (3, 24, False)
    assert (stored["max_grid"], stored["samples"], stored["seed"]) == (256, 20_000, 7)
    assert (stored["feature_strength"], stored["max_error"], stored["bits"]) == (0.0, 0.25, 12)


# ---------------------------------------------------------------------- the stages
def test_stage_weights_are_shares_summing_to_one():
    assert STAGE_NAMES == ("load", "project", "features", "sections", "linear", "refine",
                           "encode", "error", "detail", "texture", "report")
    assert all(s.weight > 0 for s in STAGES)
    assert sum(s.weight for s in STAGES) == pytest.approx(1.0, abs=1e-12)
    assert overall_progress("load", 0.0) == 0.0
    assert overall_progress("report", 1.0) == pytest.approx(1.0)
    assert overall_progress("detail", 0.5) == pytest.approx(
        sum(s.weight for s in STAGES[:8]) + 0.5 * STAGES[8].weight)


def test_an_unlisted_stage_is_refused():
    with pytest.raises(ValueError, match="stage must be one of load, project"):
        _Stages(None).start("bundle")
    with pytest.raises(ValueError, match="stage must be one of"):
        overall_progress("publish", 0.5)


class _Catalog:
    """The one catalog method ``_ProgressWriter`` calls."""

    def report_progress(self, job_id: int, stage: str, progress: float) -> None:
        pass


def test_fit_scan_reports_listed_stages_in_order_and_the_job_bar_moves_through_detail(
        tmp_path):
    writer = _ProgressWriter(_Catalog(), 1)
    seen: list[tuple[str, float, float]] = []

    def progress(stage: str, fraction: float) -> None:
        writer(stage, fraction)
        seen.append((stage, fraction, writer.best))

    bundle = fit_scan(relief_scan(20_000), tmp_path / "b", FitOptions(grid=(20, 20)), progress)
    stages = [s for s, _, _ in seen]
    assert set(stages) <= set(STAGE_NAMES)
    order = [STAGE_NAMES.index(s) for s in dict.fromkeys(stages)]
    assert order == sorted(order) and set(stages) == set(STAGE_NAMES)  # tessera: every stage
    assert list(bundle.manifest["timings"]) == list(STAGE_NAMES)
    assert bundle.manifest["tiles"]["detail"]["levels"]  # the detail stage had work to do
    first_report = stages.index("report")
    before_report = max(best for _, _, best in seen[:first_report])
    at_detail = next(best for s, _, best in seen if s == "detail")
    weight = {s.name: s.weight for s in STAGES}
    # before: detail and texture had no weight and the bar sat at load..error's share (0.92)
    # through both; now it moves by their shares and reaches 1 - w(report) before report
    assert before_report == pytest.approx(1.0 - weight["report"])
    assert before_report - at_detail == pytest.approx(weight["detail"] + weight["texture"])
    detail_values = [best for s, f, best in seen if s == "detail"]
    assert len(set(detail_values)) > 2  # it rises level by level, not in one jump
    assert writer.best == 0.99  # the writer keeps the last percent for the job's publish


def test_the_options_and_stages_modules_load_no_numpy():
    code = ("import sys; import fitter.fitting.options, fitter.fitting.stages; "
            "print(sorted(m for m in ('numpy', 'scipy', 'fitter.fitting.pipeline') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]"
