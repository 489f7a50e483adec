"""The ``tessera`` command line: ``fit``, ``tessellate`` and ``serve``.

Each subcommand is a ``_cmd_*`` function taking the parsed arguments and
returning an exit status; errors the user can fix (bad files, bad options)
print one line on stderr and exit with status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from client_py import PatchFormatError, read_patch, tessellate_grid, write_ply


class UserError(Exception):
    """A problem with the user's input or options, reported without a traceback."""


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 2:
        raise argparse.ArgumentTypeError(f"must be at least 2, got {value}")
    return value


def _patch_path(path: Path) -> Path:
    """A ``.tsp`` file, or a bundle directory's ``base.tsp``."""
    if path.is_dir():
        path = path / "base.tsp"
    if not path.is_file():
        raise UserError(f"{path}: no such patch file (give a .tsp file or a bundle directory)")
    return path


def _cmd_tessellate(args: argparse.Namespace) -> int:
    path = _patch_path(Path(args.input))
    try:
        surface = read_patch(path.read_bytes())
    except PatchFormatError as exc:
        raise UserError(f"{path}: {exc}") from None
    mesh = tessellate_grid(surface.to_scan_frame(), args.resolution, args.resolution)
    comments = [f"source {path.name}"]
    if "units" in surface.metadata:
        comments.append(f"units {surface.metadata['units']}")
    data = write_ply(mesh, binary=not args.ascii, comments=comments)
    out = Path(args.output)
    out.write_bytes(data)
    print(f"{out}: {mesh.vertex_count} vertices, {mesh.triangle_count} triangles, "
          f"{len(data)} bytes")
    return 0


def _grid(text: str) -> tuple[int, int]:
    try:
        parts = [int(x) for x in text.lower().split("x")]
    except ValueError:
        parts = []
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected NxM such as 40x40, got {text!r}")
    return parts[0], parts[1]


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
    return value


def _cmd_fit(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .io import ScanError
    from .pipeline import FitOptions, fit_scan

    options = FitOptions(grid=args.grid, degree=args.degree, method=args.method, bits=args.bits,
                         max_error=args.max_error, projection=args.projection, title=args.title)
    bars: dict[str, tqdm] = {}

    def progress(stage: str, fraction: float) -> None:
        if args.quiet:
            return
        bar = bars.get(stage)
        if bar is None:
            bar = bars[stage] = tqdm(total=100, desc=f"{stage:>9}", leave=True, file=sys.stderr,
                                     bar_format="{desc} |{bar}| {percentage:3.0f}% {elapsed}")
        bar.n = int(round(100 * fraction))
        bar.refresh()
        if fraction >= 1.0:
            bar.close()

    try:
        bundle = fit_scan(args.scan, args.output, options, progress)
    except (ScanError, ValueError) as exc:
        raise UserError(str(exc)) from None
    finally:
        for bar in bars.values():
            bar.close()
    m = bundle.manifest
    s, units = m["stats"], m["units"]
    rows = [
        ("bundle", str(bundle.path)),
        ("points", f"{m['provenance']['points']:,}"),
        ("projection", f"{m['projection']['kind']}, covers "
                       f"{100 * m['projection']['coverage']:.1f}% of the points"),
        ("patch", f"{m['base']['grid'][0]}x{m['base']['grid'][1]} degree {m['base']['degree'][0]}"
                  f"{', rational' if m['base']['rational'] else ''}: "
                  f"{m['files']['base.tsp']:,} bytes"),
        ("RMS", f"{s['rms']:.4g} {units} ({100 * s['rms_relative']:.3f}% of the diagonal)"),
        ("mean |d|", f"{s['mean']:.4g} {units}"),
        ("P95 / P99", f"{s['p95']:.4g} / {s['p99']:.4g} {units}"),
        ("max", f"{s['max']:.4g} {units} ({100 * s['max_relative']:.3f}% of the diagonal)"),
        ("time", f"{sum(m['timings'].values()):.2f} s"),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:>{width}}  {value}")
    return 0


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number, got {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be 0 to 65535, got {value}")
    return value


def _cmd_serve(args: argparse.Namespace) -> int:
    from werkzeug.serving import run_simple

    from .server import create_app

    collection = Path(args.collection)
    if not collection.is_dir():
        raise UserError(f"{collection}: not a directory "
                        "(give a folder of bundles from `tessera fit`)")
    try:
        app = create_app({"TESSERA_COLLECTION": str(collection)})
    except ValueError as exc:
        raise UserError(str(exc)) from None
    snapshot = app.extensions["tessera_snapshot"]
    if snapshot is not None:
        snapshot.start_background_build()  # the viewer's fast start, made once with node
    count = len(app.extensions["tessera_collection"].bundles())
    print(f"serving {count} object(s) from {collection} at http://{args.host}:{args.port}/ "
          "(Ctrl-C to stop)")
    run_simple(args.host, args.port, app, threaded=True)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tessera",
        description="Turn heritage scans into tiny NURBS patches and view them in a browser.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    fit = sub.add_parser(
        "fit",
        help="fit a scan with a NURBS patch and write a bundle",
        description="Fit a scan (PLY, OBJ, STL, OFF, GLB/glTF, XYZ/PTS/ASC, .gz, Stanford .conf) "
        "with one NURBS patch following Curkovic, Vucina et al., and write OUTDIR: "
        "manifest.json, base.tsp, error.png, error.ply.",
    )
    fit.add_argument("scan", help="the scan file")
    fit.add_argument("-o", "--output", required=True, help="bundle directory to write")
    fit.add_argument("--grid", type=_grid, default=(40, 40),
                     help="control points per side, NxM (default 40x40)")
    fit.add_argument("--degree", type=int, default=2, help="B-spline degree (default 2)")
    fit.add_argument("--method", choices=("tessera", "paper", "linear"), default="tessera",
                     help="tessera (default): parameter correction on the scan itself and "
                     "weights; paper: the published method as a baseline; linear: the "
                     "paper's initial linear fit alone")
    fit.add_argument("--max-error", type=_positive_float, default=None,
                     help="grow the control grid until the RMS deviation (scan units) is at "
                     "most this")
    fit.add_argument("--bits", type=int, default=None,
                     help="quantisation bits per control-point axis, 8..24 (default: the "
                          "fewest that keep the RMS within 0.5%%)")
    fit.add_argument("--projection", choices=("auto", "plane", "cylinder", "sphere"),
                     default="auto", help="map to the parameter domain (default auto)")
    fit.add_argument("--title", default=None, help="object title (default: the file name)")
    fit.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    fit.set_defaults(run=_cmd_fit)

    tess = sub.add_parser(
        "tessellate",
        help="tessellate a patch (or a bundle's base.tsp) into a PLY mesh",
        description="Tessellate a .tsp patch into a triangle mesh in the scan's own "
        "coordinates and units (the bundle's stored transform applied), written as "
        "PLY that 3DHOP, MeshLab and trimesh read.",
    )
    tess.add_argument("input", help="a .tsp patch file or a bundle directory (uses base.tsp)")
    tess.add_argument("-o", "--output", required=True, help="output .ply path")
    tess.add_argument("--resolution", type=_positive_int, default=256,
                      help="vertices per side of the parameter grid (default 256)")
    tess.add_argument("--ascii", action="store_true",
                      help="write ASCII PLY instead of binary little-endian")
    tess.set_defaults(run=_cmd_tessellate)

    serve = sub.add_parser(
        "serve",
        help="serve a collection of bundles: gallery, browser viewer, 3DHOP pages, JSON API",
        description="Serve a directory of bundles (each the output of `tessera fit`) to web "
        "browsers: a gallery, a viewer per object (the mesh is tessellated in the browser), "
        "3DHOP pages and /api/objects. Settings come from TESSERA_* environment variables "
        "(see fitter.server.DEFAULTS), e.g. TESSERA_3DHOP_DIR.",
    )
    serve.add_argument("collection", help="directory of bundle directories")
    serve.add_argument("--host", default="127.0.0.1",
                       help="address to listen on (default 127.0.0.1; 0.0.0.0 for all)")
    serve.add_argument("--port", type=_port, default=8000, help="port (default 8000)")
    serve.set_defaults(run=_cmd_serve)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except UserError as exc:
        print(f"tessera {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"tessera {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
