"""The options of one fit: ONE table (:data:`OPTIONS`) of every option's name, type, default,
accepted values, help text and spelling on the command line and in the admin's upload form.

Everything else is read from it: :class:`FitOptions` (the dataclass ``fit_scan`` takes and
the manifest records) and its :meth:`FitOptions.validate`; the CLI's arguments
(:func:`add_arguments`, :func:`from_args`); the upload form's fields (:func:`form_fields`
for the template, :func:`parse_form` for the posted values); a job's stored options
(:func:`stored_options`, :func:`fit_options`). The CLI, the form and Python therefore have
the same defaults and refuse the same values with the same messages.

Only the standard library here: the server's admin form imports this module, and a serving
process must never load numpy or scipy (``fitter.fitting`` imports nothing in its
``__init__``).

Two rules join two options, and live in :meth:`FitOptions.validate` alone: each side of
``grid`` is at least ``degree + 1``; ``max_grid``, when given, is at least the grid's largest
side. ``max_grid = None`` (the default everywhere) means :attr:`FitOptions.largest_grid`
``= max(128, max(grid))``.
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

from client_py.errors import TesseraError
from client_py.format import MAX_CONTROL_POINTS, MAX_GRID_SIDE

METHODS = ("tessera", "paper", "linear")
#: ``auto`` and the maps of ``fitter.fitting.parameterize.KINDS`` (tests/test_options.py
#: checks that the two agree; that module needs numpy, this one must not)
PROJECTIONS = ("auto", "plane", "cylinder", "sphere")
#: an atlas's base (``fitter.fitting.atlas.smooth``, ``fitter.fitting.atlas.fit``); the
#: default is the ``base`` option's in :data:`OPTIONS`
ATLAS_BASES = ("smooth", "patches")
#: ``auto`` and the axes of ``fitter.fitting.orient.AXES`` (tests/test_orient.py checks that
#: the two agree)
UP_AXES = ("auto", "+x", "-x", "+y", "-y", "+z", "-z")
GRID_SIDE_LIMIT = MAX_GRID_SIDE  # what a .tsp holds (client_py.format.LIMITS), per side
DEFAULT_MAX_GRID = 128  # max_grid = None: the grid grows to max(128, its largest side)
FIT_SAMPLE = 60_000  # default of samples
DETAIL_SPANS = 16  # default of detail_spans (= fitter.fitting.detail.SPANS, checked by a test)
#: the most patches of an atlas the fitter makes: three quads per layout (or control)
#: triangle, of at most ``fitter.fitting.atlas.fit.AUTO_MAX_TRIANGLES = MAX_PATCHES // 3``
#: triangles (a bundle holds up to ``client_py.atlas.MAX_ATLAS_QUADS``; a patches base of
#: as many stays within the ``.tsa`` limit of 2^18 control points, 9 a patch)
MAX_PATCHES = 3 * 9000
KINDS = ("grid", "int", "float", "choice", "bool", "text")
#: the upload form's groups of fields, in order: (group, legend)
FORM_GROUPS = (("object", "Object"), ("base", "Fit options"), ("layers", "Detail and texture"),
               ("sampling", "Sampling of the tessera method"))



class OptionError(TesseraError, ValueError):
    """A fit option with a value outside what :data:`OPTIONS` accepts (the message names the
    option, the value and what would be accepted)."""


_GRID_TEXT = re.compile(r"(\d+)(?:\s*[xX×]\s*(\d+))?")
_TRUE, _FALSE = ("yes", "true", "on", "1"), ("no", "false", "off", "0")


@dataclass(frozen=True)
class Option:
    """One fit option.

    name : the ``FitOptions`` field (and the manifest's ``options`` key);
    kind : one of :data:`KINDS`; default : its value when not given;
    minimum, maximum : the accepted range of an ``int`` or ``float`` (of each side for
    ``grid``), ``minimum`` exclusive when ``exclusive_minimum``; choices : of a ``choice``;
    none : what ``None`` means when ``None`` is accepted (``None``: not accepted);
    label, help : the form's label and the help of both entry points;
    cli : the command-line flag (``None``: not on the command line);
    form : the form field (``None``: not in the form); group : the form's group;
    per_object : an option of one object (its title, its description): on ``tessera fit``
    and in the upload form, not on ``tessera fit-collection``, whose options every object
    shares; multiline : a ``text`` the form edits in a text area (else one line, no control
    characters). The ``maximum`` of a ``text`` is its longest length in characters;
    atlas : the atlas fit uses it (``False``: an option of the single patch's fit alone,
    which a whole object fitted as an atlas does not use: :func:`unused_by_atlas`).
    """

    name: str
    kind: str
    default: Any
    label: str
    help: str
    minimum: float | None = None
    maximum: float | None = None
    exclusive_minimum: bool = False
    choices: tuple[str, ...] = ()
    none: str | None = None
    cli: str | None = None
    form: str | None = None
    group: str = "base"
    per_object: bool = False
    multiline: bool = False
    atlas: bool = True

    @property
    def described(self) -> str:
        """``help`` as both entry points show it: saying so when an atlas does not use it."""
        return self.help if self.atlas else f"{self.help} (a single patch; not an atlas)"

    def accepted(self, none: bool = True) -> str:
        """What values are accepted, as the refusal messages say it (with what ``None``
        means when ``none``; text typed on the command line or in a form cannot be None)."""
        if self.kind == "grid":
            text = f"two integers, each in {self.minimum}..{self.maximum}"
        elif self.kind == "int":
            text = f"an integer in {self.minimum}..{self.maximum}"
        elif self.kind == "float" and self.exclusive_minimum and self.maximum is None:
            text = f"a number greater than {self.minimum:g}"
        elif self.kind == "float":
            text = f"a number in {self.minimum:g}..{self.maximum:g}"
        elif self.kind == "choice":
            text = f"one of {', '.join(self.choices)}"
        elif self.kind == "bool":
            text = "True or False"
        else:
            text = (f"text of at most {self.maximum} characters"
                    + ("" if self.multiline else " on one line"))
        return text if self.none is None or not none else f"{text} (or None: {self.none})"

    def check(self, value: Any) -> None:
        """Refuse ``value`` unless this option accepts it (type, range, choices).

        Raises
        ------
        OptionError
            Naming the option, the value and what is accepted.
        """
        if value is None and self.none is not None:
            return
        if not self._accepts(value):
            raise OptionError(f"{self.name} must be {self.accepted()}, got {value!r}")

    def _refuse_text(self, text: str) -> OptionError:
        return OptionError(f"{self.name} must be {self.accepted(none=False)}, got {text!r}")

    def _accepts(self, value: Any) -> bool:
        if self.kind == "grid":
            return (isinstance(value, tuple | list) and len(value) == 2
                    and all(_is_int(g) and self.minimum <= g <= self.maximum for g in value))
        if self.kind == "int":
            return _is_int(value) and self.minimum <= value <= self.maximum
        if self.kind == "float":
            if not (isinstance(value, int | float) and not isinstance(value, bool)
                    and math.isfinite(value)):
                return False
            above = value > self.minimum if self.exclusive_minimum else value >= self.minimum
            return above and (self.maximum is None or value <= self.maximum)
        if self.kind == "choice":
            return isinstance(value, str) and value in self.choices
        if self.kind == "bool":
            return isinstance(value, bool)
        return (isinstance(value, str) and len(value) <= self.maximum
                and (self.multiline or not any(ord(c) < 32 or ord(c) == 127 for c in value)))

    def parse(self, text: str) -> Any:
        """The value of ``text`` as typed on the command line or in the form, checked.

        ``grid``: ``N`` or ``NxM``; ``bool``: ``yes``/``no`` (also true/false, on/off, 1/0);
        an ``int`` that accepts ``None``: also ``auto`` (for ``None``).

        Raises
        ------
        OptionError
            Naming the option, the text and what is accepted.
        """
        text = text.strip()
        if self.kind == "grid":
            match = _GRID_TEXT.fullmatch(text)
            if match is None:
                raise OptionError(f"{self.name} must be N or NxM such as 40x40, got {text!r}")
            value: Any = (int(match[1]), int(match[2] or match[1]))
        elif self.kind == "int" and self.none is not None and text.lower() == "auto":
            return None  # what None means is written in ``none``
        elif self.kind == "int":
            try:
                value = int(text)
            except ValueError:
                raise self._refuse_text(text) from None
        elif self.kind == "float":
            try:
                value = float(text)
            except ValueError:
                raise self._refuse_text(text) from None
        elif self.kind == "bool":
            if text.lower() not in _TRUE + _FALSE:
                raise OptionError(f"{self.name} must be yes or no, got {text!r}")
            value = text.lower() in _TRUE
        else:
            value = text
        if not self._accepts(value):
            raise self._refuse_text(text)
        return value

    def text(self, value: Any) -> str:
        """``value`` as the form shows it (``""`` for ``None``); :meth:`parse` reads it back."""
        if value is None:
            return ""
        if self.kind == "grid":
            return f"{value[0]}x{value[1]}"
        if self.kind == "bool":
            return "yes" if value else "no"
        return f"{value:g}" if self.kind == "float" else str(value)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


OPTIONS: tuple[Option, ...] = (
    Option("grid", "grid", (40, 40), "Control grid",
           "control points per side, N or NxM (each side at least degree + 1)",
           minimum=2, maximum=GRID_SIDE_LIMIT, cli="--grid", form="grid", atlas=False),
    Option("degree", "int", 2, "Degree", "B-spline degree of the patch",
           minimum=1, maximum=5, cli="--degree", form="degree", atlas=False),
    Option("method", "choice", "tessera", "Method",
           "tessera: parameter correction on the scan itself, then weights; paper: the "
           "published method, a baseline; linear: the paper's initial linear fit alone",
           choices=METHODS, cli="--method", form="method", atlas=False),
    Option("bits", "int", None, "Bits",
           "quantisation bits per control-point axis (automatic: the fewest that keep a single "
           "patch's RMS within 0.5%; an atlas's step at 1.2x its RMS)",
           minimum=8, maximum=24, none="automatic", cli="--bits", form="bits"),
    Option("max_error", "float", None, "Target RMS (scan units)",
           "grow the control grid (x1.25 per side) until the RMS deviation in scan units is "
           "at most this", minimum=0, exclusive_minimum=True, none="no target",
           cli="--max-error", form="max_error", atlas=False),
    Option("max_grid", "int", None, "Largest grid",
           "the largest control grid side the target RMS may grow to (at least the grid's "
           "largest side)", minimum=2, maximum=GRID_SIDE_LIMIT,
           none=f"max({DEFAULT_MAX_GRID}, largest grid side)",
           cli="--max-grid", form="max_grid", atlas=False),
    Option("patches", "int", None, "Patches",
           "NURBS patches of the atlas that covers the whole object (about; 1: a single "
           "height-field patch, bundle format 1; an atlas has at least 3)", minimum=1,
           maximum=MAX_PATCHES,
           none="auto: one patch for a height field (a cloud's alone on the smooth base), "
           "else an atlas sized for the object",
           cli="--patches", form="patches"),
    Option("base", "choice", "smooth", "Atlas base",
           "the whole object's base: smooth (a triangle control mesh drawn as Catmull-Clark "
           "patches: fewer bytes for its error; with patches auto every mesh is an atlas) "
           "or patches (bicubic patches stored point by point, joined C0)",
           choices=ATLAS_BASES, cli="--base", form="base"),
    Option("projection", "choice", "auto", "Projection", "map to the parameter domain",
           choices=PROJECTIONS, cli="--projection", form="projection",
           atlas=False),
    Option("up", "choice", "auto", "Up direction",
           "the object's up axis in scan coordinates for the first view and the thumbnail "
           "(auto: the format's axis, else a flat base, else +y)", choices=UP_AXES,
           cli="--up", form="up"),
    Option("title", "text", None, "Title", "the object's title", maximum=200,
           none="the scan's file name", cli="--title", form="title", group="object",
           per_object=True),
    Option("description", "text", None, "Description",
           "what the object is, shown in the viewer's panel", maximum=10_000, none="none",
           cli="--description", form="description", group="object", per_object=True,
           multiline=True),
    Option("units", "text", None, "Units",
           "the scan's length unit, e.g. mm or m", maximum=20,
           none="what the file says (PLY, OBJ or XYZ header comments, glTF: m), else unknown",
           cli="--units", form="units", group="object"),
    Option("feature_strength", "float", 4.0, "Feature strength",
           "how much denser the tessera method samples where local PCA finds features "
           "(0: uniform)", minimum=0, maximum=100, cli="--feature-strength",
           form="feature_strength", group="sampling", atlas=False),
    Option("seed", "int", 0, "Seed", "seed of the tessera method's sample",
           minimum=0, maximum=2**32 - 1, cli="--seed", form="seed", group="sampling",
           atlas=False),
    Option("samples", "int", FIT_SAMPLE, "Samples",
           "scan points the tessera refinement fits", minimum=1000, maximum=10_000_000,
           cli="--samples", form="samples", group="sampling", atlas=False),
    Option("detail_levels", "int", None, "Detail levels",
           "levels of the detail pyramid (an atlas holds at most 4, fewer of many patches)",
           minimum=0, maximum=8, none="as the point density allows",
           cli="--detail-levels", form="detail_levels", group="layers"),
    Option("detail_spans", "int", DETAIL_SPANS, "Detail spans",
           "knot spans per detail tile side (level k has this times 2^k spans across the "
           "object; an atlas's tiles have 8 a patch side)", minimum=4, maximum=64,
           cli="--detail-spans", form="detail_spans", group="layers", atlas=False),
    Option("texture", "bool", True, "Texture",
           "write the texture pyramid when the scan has colour", cli="--texture",
           form="texture", group="layers"),
)
#: the options by name
OPTION = {o.name: o for o in OPTIONS}
_DEFAULT = {o.name: o.default for o in OPTIONS}


@dataclass
class FitOptions:
    """Options of one fit (recorded in the manifest); the fields, their defaults and the
    values accepted are those of :data:`OPTIONS`:

    grid : control points per side ``(n_u, n_v)``; degree : ``p = q``; method :
    ``tessera`` (default, the best we have), ``paper`` (as published) or ``linear``
    (the paper's initial linear solution alone, a baseline); bits : quantisation of the
    patch file, or ``None`` for the fewest bits that keep the fit's RMS within 0.5 %
    (``fitter.fitting.compact``; an atlas: a step of
    ``fitter.fitting.atlas.fit.BASE_STEP_OVER_RMS`` times its RMS); max_error : target
    RMS in scan units (grows the grid);
    max_grid : cap for that growth (``None``: :attr:`largest_grid`); patches : of the atlas
    (``None``: ``fitter.fitting.atlas.pipeline.wants_atlas`` decides; 1: one patch); base :
    an atlas's base, ``smooth`` (default) or ``patches`` (:data:`ATLAS_BASES`);
    projection : ``auto`` or a map; up : the object's up axis (``auto``: found by
    ``fitter.fitting.orient``);
    title : the object's title; description : what it is; units : the scan's length unit
    (``None``: what the file says, ``fitter.fitting.io``; it labels every length the bundle
    records); feature_strength : how much denser the tessera
    method samples where local PCA finds features (0: uniform); seed, samples : of the
    scan points the tessera refinement fits; detail_levels : depth of the detail pyramid
    (``None``: as the point density allows); detail_spans : knot spans per detail tile
    side (level ``k`` has ``detail_spans 2^k`` per side of the domain); texture : the
    colour pyramid.
    """

    grid: tuple[int, int] = _DEFAULT["grid"]
    degree: int = _DEFAULT["degree"]
    method: str = _DEFAULT["method"]
    bits: int | None = _DEFAULT["bits"]
    max_error: float | None = _DEFAULT["max_error"]
    max_grid: int | None = _DEFAULT["max_grid"]
    patches: int | None = _DEFAULT["patches"]
    base: str = _DEFAULT["base"]
    projection: str = _DEFAULT["projection"]
    up: str = _DEFAULT["up"]
    title: str | None = _DEFAULT["title"]
    description: str | None = _DEFAULT["description"]
    units: str | None = _DEFAULT["units"]
    feature_strength: float = _DEFAULT["feature_strength"]
    seed: int = _DEFAULT["seed"]
    samples: int = _DEFAULT["samples"]
    detail_levels: int | None = _DEFAULT["detail_levels"]
    detail_spans: int = _DEFAULT["detail_spans"]
    texture: bool = _DEFAULT["texture"]

    def __post_init__(self) -> None:
        if isinstance(self.grid, list):  # as stored in JSON
            self.grid = tuple(self.grid)

    @property
    def largest_grid(self) -> int:
        """The largest control grid side ``max_error`` may grow to:
        ``max_grid``, or ``max(128, max(grid))`` when ``max_grid`` is ``None``."""
        if self.max_grid is not None:
            return self.max_grid
        return max(DEFAULT_MAX_GRID, *self.grid)

    def validate(self) -> None:
        """Check every option against :data:`OPTIONS`, then the rules no one range says: the
        grid against the degree and the patch file's size, ``max_grid`` against the grid, and
        no atlas of 2 patches.

        Raises
        ------
        OptionError
            The first option refused, naming it, the value and what is accepted.
        """
        for option in OPTIONS:
            option.check(getattr(self, option.name))
        lowest = self.degree + 1
        if min(self.grid) < lowest:
            raise OptionError(f"grid {self.grid[0]}x{self.grid[1]}: each side must be in "
                             f"{lowest}..{GRID_SIDE_LIMIT} for degree {self.degree}")
        if self.grid[0] * self.grid[1] > MAX_CONTROL_POINTS:
            raise OptionError(f"grid {self.grid[0]}x{self.grid[1]} has "
                              f"{self.grid[0] * self.grid[1]} control points; a patch holds at "
                              f"most {MAX_CONTROL_POINTS} (client_py.format.LIMITS)")
        if self.patches == 2:
            raise OptionError(f"patches 2: 1 is a single height-field patch; an atlas has "
                              f"3..{MAX_PATCHES} (three quads per layout triangle)")
        if self.max_grid is not None and self.max_grid < max(self.grid):
            raise OptionError(f"max_grid must be an integer in {max(self.grid)}.."
                             f"{GRID_SIDE_LIMIT} (at least the grid's largest side), "
                             f"got {self.max_grid!r}")


def unused_by_atlas(options: FitOptions) -> list[str]:
    """The options ``options`` sets (not to their defaults) that a whole object fitted as an
    atlas does not use (``Option.atlas`` false: the single patch's grid, map, sampling and
    tile spans), by name in table order; the atlas manifest's ``options_unused``."""
    return [o.name for o in OPTIONS
            if not o.atlas and getattr(options, o.name) != o.default]


def stored_options(options: FitOptions) -> dict[str, Any]:
    """``options`` as the manifest and a job record them: a JSON object (tuples as lists)."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(options).items()}


def fit_options(stored: Mapping[str, Any]) -> FitOptions:
    """Validated ``FitOptions`` from stored options (:func:`stored_options`, a job's record);
    missing options take their defaults.

    Raises
    ------
    OptionError
        An unknown option or a refused value, naming it.
    """
    unknown = sorted(set(stored) - set(OPTION))
    if unknown:
        raise OptionError(f"unknown fit option(s) {', '.join(unknown)}; accepted: "
                         f"{', '.join(OPTION)}")
    options = FitOptions(**stored)
    options.validate()
    return options


# ------------------------------------------------------------------------ command line
def _help(option: Option) -> str:
    if option.none is not None and option.default is None:
        default = option.none
    elif option.kind == "bool":
        default = "yes" if option.default else "no"
    else:
        default = option.text(option.default)
    accepted = (f"; {option.minimum}..{option.maximum}" if option.kind == "int" else "")
    return f"{option.described}{accepted} (default: {default})".replace("%", "%%")


def _argument_type(option: Option):  # noqa: ANN202 - an argparse type function
    def parse(text: str) -> Any:
        try:
            return option.parse(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    parse.__name__ = option.name
    return parse


def add_arguments(parser: argparse.ArgumentParser, collection: bool = False) -> None:
    """Add every option of :data:`OPTIONS` that has a command-line spelling to ``parser``
    (``--grid 40x40``, ``--max-error 0.1``, ``--texture``/``--no-texture`` ...), each with
    the table's default and its checks (argparse exits with status 2 and the message);
    with ``collection`` (``tessera fit-collection``), not the per-object ones (``--title``,
    ``--description``)."""
    for option in OPTIONS:
        if option.cli is None or (collection and option.per_object):
            continue
        if option.kind == "bool":
            parser.add_argument(option.cli, dest=option.name, default=option.default,
                                action=argparse.BooleanOptionalAction, help=_help(option))
        else:
            metavar = ("{" + ",".join(option.choices) + "}" if option.kind == "choice"
                       else "NxM" if option.kind == "grid" else option.name.upper())
            parser.add_argument(option.cli, dest=option.name, default=option.default,
                                type=_argument_type(option), metavar=metavar,
                                help=_help(option))


def from_args(args: argparse.Namespace, **extra: Any) -> FitOptions:
    """Validated ``FitOptions`` from the arguments :func:`add_arguments` added (those it left
    out take their defaults), plus ``extra`` options.

    Raises
    ------
    OptionError
        A rule joining two options refused (e.g. ``--grid 3x3 --degree 3``).
    """
    values = {o.name: getattr(args, o.name) for o in OPTIONS
              if o.cli is not None and hasattr(args, o.name)}
    options = FitOptions(**values, **extra)
    options.validate()
    return options


# --------------------------------------------------------------------- the upload form
def form_fields() -> list[dict[str, Any]]:
    """The upload form's fields, in table order, for the template: ``name``, ``label``,
    ``help``, ``group`` (of :data:`FORM_GROUPS`), ``input`` (``text``, ``textarea``,
    ``number`` or ``select``), ``value`` (the default as text, ``""`` for ``None``),
    ``placeholder`` (what an empty field means), ``choices``, ``min``, ``max``, ``step``,
    ``pattern``, ``maxlength`` (of a text)."""
    fields = []
    for option in OPTIONS:
        if option.form is None:
            continue
        entry: dict[str, Any] = {
            "name": option.form, "label": option.label, "help": option.described,
            "group": option.group, "value": option.text(option.default),
            "placeholder": option.none or "", "choices": (), "min": None, "max": None,
            "step": None, "pattern": None, "maxlength": None, "input": "number"}
        if option.kind == "grid":
            entry.update(input="text", pattern=r"\d+\s*([xX×]\s*\d+)?",
                         placeholder="N or NxM, e.g. 40x40")
        elif option.kind == "choice":
            entry.update(input="select", choices=option.choices)
        elif option.kind == "bool":
            entry.update(input="select", choices=("yes", "no"))
        elif option.kind == "int":
            entry.update(min=option.minimum, max=option.maximum, step=1)
        elif option.kind == "float":
            entry.update(min=option.minimum, max=option.maximum, step="any")
        else:
            entry.update(input="textarea" if option.multiline else "text",
                         maxlength=option.maximum)
        fields.append(entry)
    return fields


def parse_form(form: Mapping[str, str], ignore: Iterable[str] = (),
               **extra: Any) -> dict[str, Any]:
    """The stored options (:func:`stored_options`) of an upload form: the option fields
    given (an empty field keeps the default), plus ``extra`` options, validated. Fields in
    ``ignore`` are the caller's (the file, the CSRF token).

    Raises
    ------
    OptionError
        An unknown field, or a value refused, naming the field.
    """
    known = {o.form: o for o in OPTIONS if o.form is not None}
    ignore = set(ignore)
    unknown = sorted(set(form) - set(known) - ignore)
    if unknown:
        raise OptionError(f"unknown form field(s) {', '.join(unknown)}; accepted: "
                         f"{', '.join(sorted(set(known) | ignore))}")
    values = {}
    for name, option in known.items():
        text = (form.get(name) or "").strip()
        if text:
            values[option.name] = option.parse(text)
    options = FitOptions(**values, **extra)
    options.validate()
    return stored_options(options)
