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
