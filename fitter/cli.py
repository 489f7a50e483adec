"""The ``tessera`` command line: ``fit``, ``tessellate``, ``serve``, ``fit-collection``, ``admin``.

Each subcommand is a ``_cmd_*`` function taking the parsed arguments and
returning an exit status; errors the user can fix (bad files, bad options)
print one line on stderr and exit with status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Callable
from pathlib import Path

from client_py import (
    PatchFormatError,
    TextureImage,
    read_detail_tile,
    read_patch,
    tessellate_grid,
    write_ply,
)
from client_py.bundle import (
    BASE_RESOLUTION,
    PLY_MAX_RESOLUTION,
    base_file,
    fit_notes,
    pieces_mesh,
    plan_level,
    read_pieces,
    scan_origin,
    write_level_ply,
)
from client_py.errors import TesseraError

from .fitting.cores import usable_cores
from .fitting.options import OptionError
from .fitting.options import add_arguments as add_fit_arguments
from .fitting.options import from_args as fit_options_from_args
from .process_exit import exit_now


class UserError(TesseraError):
    """A problem with the user's input or options, reported without a traceback."""


def _integer(lo: int, hi: int | None = None, what: str = "an integer",
             lo_meaning: str = "") -> Callable[[str], int]:
    """An argparse type: an integer in ``lo..hi`` (no upper bound when ``hi`` is None)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if hi is None and value < lo:
            raise argparse.ArgumentTypeError(f"must be {lo}{lo_meaning} or more, got {value}")
        if hi is not None and not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be {lo} to {hi}, got {value}")
        return value
    return parse


_resolution = _integer(2)
_count = _integer(1)
_level = _integer(-1, lo_meaning=" (the base alone)")
_port = _integer(0, 65535, "a port number")


def _patch_path(path: Path) -> Path:
    """A ``.tsp`` file, or a bundle directory's ``base.tsp``."""
    if path.is_dir():
        path = path / "base.tsp"
    if not path.is_file():
        raise UserError(f"{path}: no such patch file (give a .tsp file or a bundle directory)")
    return path


def _cmd_tessellate(args: argparse.Namespace) -> int:
    bundle = Path(args.input)
    if bundle.is_dir() and (bundle / "manifest.json").is_file():
        return _tessellate_bundle(args, bundle)
    if args.level is not None or args.texture:
        raise UserError(f"{bundle}: --level and --texture need a bundle directory "
                        "(with manifest.json)")
    path = _patch_path(bundle)
    try:
        surface = read_patch(path.read_bytes())
    except PatchFormatError as exc:
        raise UserError(f"{path}: {exc}") from None
    resolution = BASE_RESOLUTION if args.resolution is None else args.resolution
    mesh = tessellate_grid(surface.to_scan_frame(), resolution, resolution)
    comments = [f"source {path.name}"]
    if "units" in surface.metadata:
        comments.append(f"units {surface.metadata['units']}")
    data = write_ply(mesh, binary=not args.ascii, comments=comments)
    out = Path(args.output)
    out.write_bytes(data)
    print(f"{out}: {mesh.vertex_count} vertices, {mesh.triangle_count} triangles, "
          f"{len(data)} bytes")
    return 0


def _tessellate_bundle(args: argparse.Namespace, bundle: Path) -> int:
    """A bundle at ``--level``, as the viewer's "Download PLY" writes it: the files and grid
    of ``client_py.bundle.plan_level`` (``--resolution`` overrides the grid) and the
    detached pieces (``client_py.bundle.read_pieces``, drawn at every level), written by
    ``client_py.bundle.write_level_ply`` with per-vertex colours from the texture tiles, or
    (``--texture``) texture uvs and the level's texture as one PNG beside the PLY."""
    import json

    from PIL import Image

    try:
        manifest = json.loads((bundle / "manifest.json").read_text())
    except (OSError, ValueError, RecursionError) as exc:  # RecursionError: nested too deep
        raise UserError(f"{bundle / 'manifest.json'}: not a readable manifest: {exc}") from None
    from client_py.bundle import manifest_version

    try:
        atlas = manifest_version(manifest) == 2
    except PatchFormatError as exc:  # ManifestError: a version this reader does not know
        raise UserError(f"{bundle}: {exc}") from None
    if atlas:
        return _tessellate_atlas_bundle(args, bundle, manifest)
    try:  # file names come confined to the bundle (client_py.bundle.check_file_name)
        plan = plan_level(manifest, args.level)
        surface = read_patch((bundle / base_file(manifest)).read_bytes())
        tiles = [read_detail_tile((bundle / name).read_bytes()) for name in plan.detail_files]
        pieces = pieces_mesh(manifest, read_pieces(manifest, lambda name: (bundle / name)
                                                   .read_bytes()))
        origin = scan_origin(manifest)
    except PatchFormatError as exc:  # a bad file or manifest (ManifestError)
        raise UserError(f"{bundle}: {exc}") from None
    except (OSError, ValueError) as exc:  # a missing file; a --level the bundle lacks
        raise UserError(f"{bundle}: {exc}") from None
    decoded = _decode_images(bundle, plan.texture_nodes)
    try:
        images = [TextureImage(node["level"], node["i"], node["j"], *decoded[node["file"]])
                  for node in plan.texture_nodes]
    except ValueError as exc:
        raise UserError(f"{bundle}: not a usable texture tile: {exc}") from None
    out = Path(args.output)
    texture_file = None
    if args.texture:
        if not images:
            raise UserError(f"{bundle}: --texture: the bundle has no texture tiles")
        side = images[0].width << images[0].level
        atlas = Image.new("RGB", (side, side))
        for im in images:  # row 0 at the top = v = 1 (docs/format.md, texture tiles)
            tile = Image.frombytes("RGB", (im.width, im.height), im.rgb)
            atlas.paste(tile, (im.i * im.width, side - (im.j + 1) * im.height))
        texture_file = f"{out.stem}_texture.png"
        atlas.save(out.with_name(texture_file))
    resolution = plan.resolution if args.resolution is None else args.resolution
    data, mesh = write_level_ply(surface, tiles, plan.level, resolution, bundle.name,
                                 () if args.texture else images, binary=not args.ascii,
                                 texture_file=texture_file, pieces=pieces, origin=origin)
    out.write_bytes(data)
    print(f"{out}: level {plan.level}, {mesh.vertex_count} vertices, {mesh.triangle_count} "
          f"triangles, {len(data)} bytes" + (f", texture {texture_file}" if texture_file else ""))
    return 0


def _decode_images(bundle: Path, nodes) -> dict[str, tuple[int, int, bytes]]:
    """``{file: (width, height, rgb)}`` of the texture images ``nodes`` name, decoded by
    Pillow (client_py decodes no images); a file that is not one is a ``UserError``."""
    from PIL import Image

    out = {}
    for node in nodes:
        try:
            with Image.open(bundle / node["file"]) as im:
                rgb = im.convert("RGB")
                out[node["file"]] = (rgb.width, rgb.height, rgb.tobytes())
        except (OSError, ValueError) as exc:  # PIL.UnidentifiedImageError is an OSError
            raise UserError(f"{bundle / node['file']}: not a usable texture image: {exc}") \
                from None
    return out


def _tessellate_atlas_bundle(args: argparse.Namespace, bundle: Path, manifest: dict) -> int:
    """An atlas bundle (manifest version 2) at ``--level``: ``base.tsa`` and the packs of
    levels ``0..L`` (``client_py.bundle.plan_level``), one welded PLY written by
    ``client_py.bundle.write_level_ply`` on the level's samples per patch side
    (``--resolution`` overrides them), as the viewer's "Download PLY" writes it; with
    colour, RGB per vertex from the level's colour packs (also with ``--texture``: an atlas
    has no one texture image to name)."""
    from client_py.atlas_format import read_atlas
    from client_py.bundle import atlas_level_detail, check_atlas_base, colour_packs_of

    def read(name: str) -> bytes:
        return (bundle / name).read_bytes()

    try:  # file names come confined to the bundle (client_py.bundle.check_file_name)
        plan = plan_level(manifest, args.level)
        atlas, metadata = read_atlas(read(base_file(manifest)))
        check_atlas_base(atlas, manifest)
        detail = atlas_level_detail(manifest, read, plan.level, atlas)
        if args.texture and not plan.texture_nodes:
            raise UserError(f"{bundle}: --texture: the bundle has no colour")
        packs = colour_packs_of(plan.texture_nodes, _decode_images(bundle, plan.texture_nodes))
        resolution = plan.resolution if args.resolution is None else args.resolution
        data, mesh = write_level_ply(atlas, detail, plan.level, resolution, bundle.name,
                                     packs, binary=not args.ascii, units=manifest.get("units")
                                     or metadata.get("units"), origin=scan_origin(manifest))
    except PatchFormatError as exc:  # a bad file or manifest (ManifestError)
        raise UserError(f"{bundle}: {exc}") from None
    except (OSError, ValueError) as exc:  # a missing file; a --level the bundle lacks
        raise UserError(f"{bundle}: {exc}") from None
    out = Path(args.output)
    out.write_bytes(data)
    print(f"{out}: level {plan.level}, {len(atlas.quads)} patches, {mesh.vertex_count} "
          f"vertices, {mesh.triangle_count} triangles, {len(data)} bytes"
          + (f", vertex colours from {len(packs)} colour packs" if packs else ""))
    return 0


@contextlib.contextmanager
def _fit_blocks(args: argparse.Namespace):  # noqa: ANN202 - a context of DaskBlocks or None
    """The runner of an out-of-core fit's block passes (``fitter.fitting.stream``): a Dask
    client of ``--scheduler``, or of a LocalCluster of ``--workers`` processes; None (this
    process's threads) without either. The bundle is the same bytes either way."""
    if not (args.scheduler or args.workers):
        yield None
        return
    from distributed import Client, LocalCluster

    from .fitting.stream import DaskBlocks

    if args.scheduler:
        with Client(args.scheduler) as client:
            yield DaskBlocks(client)
        return
    with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        yield DaskBlocks(client)


def _cmd_fit(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .fitting.io import ScanError
    from .fitting.pipeline import fit_scan

    options = _fit_options(args)
    bars: dict[str, tqdm] = {}

    def progress(stage: str, fraction: float, points: int | None = None) -> None:
        if args.quiet:
            return
        bar = bars.get(stage)
        if bar is None:
            bar = bars[stage] = tqdm(total=100, desc=f"{stage:>9}", leave=True, file=sys.stderr,
                                     bar_format="{desc} |{bar}| {percentage:3.0f}% "
                                                "{elapsed}<{remaining}{postfix}")
        bar.n = int(round(100 * fraction))
        if points is not None:  # a streamed pass (fitter.fitting.stream): its rate
            elapsed = bar.format_dict["elapsed"]
            bar.set_postfix_str(f"{points / max(elapsed, 1e-9) / 1e6:.2f} M points/s",
                                refresh=False)
        bar.refresh()
        if fraction >= 1.0:
            bar.close()

    try:
        with _fit_blocks(args) as blocks:
            bundle = fit_scan(args.scan, args.output, options, progress,
                              limits=_input_limits(args), memory_budget=args.memory_budget,
                              blocks=blocks)
    except (ScanError, OptionError) as exc:
        raise UserError(str(exc)) from None
    finally:
        for bar in bars.values():
            bar.close()
    m = bundle.manifest
    s, units = m["stats"], m["units"]
    rows = [
        ("bundle", str(bundle.path)),
        ("points", f"{m['provenance']['points']:,}"),
        *_base_rows(m),
        ("RMS", f"{s['rms']:.4g} {units} ({100 * s['rms_relative']:.3f}% of the diagonal)"),
        ("mean |d|", f"{s['mean']:.4g} {units}"),
        ("P95 / P99", f"{s['p95']:.4g} / {s['p99']:.4g} {units}"),
        ("max", f"{s['max']:.4g} {units} ({100 * s['max_relative']:.3f}% of the diagonal)"),
        *_layer_rows(m),
        *fit_notes(m),
        ("time", f"{sum(m['timings'].values()):.2f} s"),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:>{width}}  {value}")
    return 0


def _base_rows(m: dict) -> list[tuple[str, str]]:
    """The summary's lines on the base: the single patch's map and grid, or the atlas."""
    base = m["base"]
    if base.get("kind") == "atlas":
        c = m["coverage"]
        return [("atlas", f"{base['patches']:,} patches of degree {base['degree']}, "
                          f"{base['spans']} span(s) a side, {base['border_edges']} open border "
                          f"edges: {m['files']['base.tsa']:,} bytes"),
                ("coverage", f"{100 * c['within_0.5%']:.2f}% of all points within 0.5% of the "
                             f"diagonal of the finest drawn level; {c['uncovered_points']:,} "
                             "farther than 1%")]
    return [("projection", f"{m['projection']['kind']}, covers "
                           f"{100 * m['projection']['coverage']:.1f}% of the points"),
            ("patch", f"{base['grid'][0]}x{base['grid'][1]} degree {base['degree'][0]}"
                      f"{', rational' if base['rational'] else ''}: "
                      f"{m['files']['base.tsp']:,} bytes")]


def _layer_rows(m: dict) -> list[tuple[str, str]]:
    tiles = m.get("tiles") or {}
    rows = []
    for lev in (tiles.get("detail") or {}).get("levels", []):
        count = (f"{lev['packs']} packs" if "packs" in lev else f"{lev['tiles']} tiles")
        rows.append((f"level {lev['level']}", f"RMS {lev['rms']:.4g}, max {lev['max']:.4g} "
                     f"{m['units']}: {count}, {lev['bytes_total']:,} bytes"))
    texture = tiles.get("texture")
    if texture:
        kind = "packs" if "packs" in texture else "tiles"  # an atlas's colour packs
        count = sum(x[kind] for x in texture["levels"])
        size = sum(x["bytes_total"] for x in texture["levels"])
        rows.append(("texture", f"{len(texture['levels'])} levels, {count} {kind}, "
                     f"{size:,} bytes"))
    return rows


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
        if args.production:
            snapshot.ensure()  # before gunicorn forks: no build thread in the arbiter
        else:
            snapshot.start_background_build()  # the viewer's fast start, made once with node
    runner = _start_job_runner(app, args.fit_workers)
    count = len(app.extensions["tessera_collection"].bundles())
    server = (f"gunicorn ({args.processes or usable_cores()} processes x {args.threads} "
              "threads)" if args.production else "the development server")
    print(f"serving {count} object(s) from {collection} at http://{args.host}:{args.port}/ "
          f"with {server}{'; admin at /admin/' if runner is not None else ''} (Ctrl-C to stop)",
          flush=True)
    try:
        if args.production:
            _serve_gunicorn(app, args)
        else:
            run_simple(args.host, args.port, app, threaded=True)
    finally:
        if runner is not None:
            runner.stop()
    return 0


def _serve_gunicorn(app, args: argparse.Namespace) -> None:  # noqa: ANN001 - a Flask app
    """Serve ``app`` with gunicorn: pre-forked processes (one per core by default), each with
    ``--threads`` request threads, so serving uses every core (one Python process is held to
    one core by the GIL). The worker is gunicorn's ``gthread`` with the admin tarpit
    (:mod:`fitter.server.tarpit_worker`: a connection that sent a refused admin token waits
    without a thread before its next request is read)."""
    from gunicorn.app.base import BaseApplication

    from .server.tarpit_worker import WORKER_CLASS

    class Application(BaseApplication):
        def load_config(self) -> None:
            settings = {"bind": f"{args.host}:{args.port}",
                        "workers": args.processes or usable_cores(),
                        "worker_class": WORKER_CLASS, "threads": args.threads,
                        "accesslog": None, "errorlog": "-", "loglevel": "warning",
                        "proc_name": "tessera-serve"}
            for key, value in settings.items():
                self.cfg.set(key, value)

        def load(self):  # noqa: ANN202 - the WSGI app
            return app

    Application().run()


def _start_job_runner(app, workers: int | None):  # noqa: ANN001, ANN202 - Flask app, runner
    """The admin's fit-job supervisor in its own process, when the admin area is on."""
    from .collection.jobs import RunnerProcess

    admin = app.extensions.get("tessera_admin")
    if admin is None or not admin.enabled:
        return None
    count = workers or int(app.config.get("TESSERA_JOB_WORKERS") or 0) or None
    # the jobs read uploads with the server's TESSERA_UPLOAD_* limits (admin.limits)
    return RunnerProcess(admin.collection, workers=count, limits=admin.limits).start()


def _cmd_admin_set_token(args: argparse.Namespace) -> int:
    import getpass
    import secrets

    from .collection.catalog import Catalog, adopt_bundles
    from .collection.tokens import TOKEN_SETTING, check_token_strength, hash_token

    collection = Path(args.collection)
    if not collection.is_dir():
        raise UserError(f"{collection}: not a directory (give the collection folder)")
    if (collection / "manifest.json").is_file():
        raise UserError(f"{collection} is a single bundle; the admin area manages a "
                        "collection folder of bundles")
    if args.generate:
        token = secrets.token_urlsafe(32)
    elif sys.stdin.isatty():
        token = getpass.getpass("new admin token: ")
        if getpass.getpass("again: ") != token:
            raise UserError("the two entries differ; nothing changed")
    else:
        token = sys.stdin.readline().strip()
    try:
        check_token_strength(token)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    with Catalog(collection, create=True) as catalog:
        if catalog.created:
            adopt_bundles(catalog, publish=True)  # what was public stays public
        catalog.set_setting(TOKEN_SETTING, hash_token(token))
    if args.generate:
        print(token)
        print("(the new admin token; only its hash is stored: keep it safe)", file=sys.stderr)
    else:
        print(f"admin token set for {collection} (stored hashed)", file=sys.stderr)
    # a running server reads the hash on its next admin request: no restart, old token void
    print("a running `tessera serve` of this collection uses it from its next admin request "
          "(unless it was started with TESSERA_ADMIN_TOKEN, which takes precedence)",
          file=sys.stderr)
    return 0


def _cmd_fit_collection(args: argparse.Namespace) -> int:
    from .collection.batch import fit_collection, format_summary

    options = _fit_options(args)
    try:
        results = fit_collection(args.scans, args.output, options, scheduler=args.scheduler,
                                 workers=args.workers, progress=not args.quiet)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    print(format_summary(results))
    return 1 if any(r.state == "failed" for r in results) else 0


def _fit_options(args: argparse.Namespace, **extra):  # noqa: ANN202 - a FitOptions
    """``FitOptions`` from the arguments ``fitter.fitting.options.add_arguments`` added to
    ``fit`` and ``fit-collection`` (each checked by argparse: exit status 2 and a message),
    with ``extra``; a rule joining two options (``--grid 3x3 --degree 3``) exits 2 too."""
    try:
        return fit_options_from_args(args, **extra)
    except OptionError as exc:
        raise UserError(str(exc)) from None


def _byte_count(text: str) -> int:
    """An argparse type: bytes as ``N``, ``NK``, ``NM`` or ``NG`` (binary units), ``>= 1``."""
    units = {"k": 1 << 10, "m": 1 << 20, "g": 1 << 30}
    scale = units.get(text.strip()[-1:].lower(), 1)
    digits = text.strip()[:-1] if scale > 1 else text.strip()
    try:
        value = int(float(digits) * scale)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of bytes such as 2G, 512M or "
                                         f"1000000, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1 byte, got {text!r}")
    return value


def _ratio(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value >= 1:  # also NaN
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text!r}")
    return value


#: the fit command's input limits: (flag, InputLimits field, argparse type, help)
INPUT_LIMIT_FLAGS = (
    ("--max-points", "max_points", _integer(1), "most points the scan (a .conf: all its "
     "scans) may hold, counted before they are allocated"),
    ("--max-expanded-bytes", "max_expanded_bytes", _byte_count, "most bytes its gzip "
     "streams may decompress to, all files together (e.g. 8G)"),
    ("--max-ratio", "max_ratio", _ratio, "largest decompressed/compressed ratio of a gzip "
     "stream"),
    ("--max-files", "max_files", _integer(1), "most scan files a .conf may name"),
)


def _add_input_limit_arguments(parser: argparse.ArgumentParser) -> None:
    """The fit command's input limits (``fitter.fitting.io.limits.InputLimits``, whose
    defaults the help shows) and its memory budget (``fitter.fitting.memory``)."""
    from .fitting.io.limits import InputLimits
    from .fitting.memory import DEFAULT_MEMORY_BUDGET

    group = parser.add_argument_group(
        "input limits", "refuse inputs past these before they are read into memory "
        "(docs/method.md, 'Input limits and the memory budget')")
    defaults = InputLimits()
    for flag, field, kind, text in INPUT_LIMIT_FLAGS:
        group.add_argument(flag, dest=field, type=kind, default=None,
                           help=f"{text} (default {getattr(defaults, field):,})")
    group.add_argument("--memory-budget", type=_byte_count, default=DEFAULT_MEMORY_BUDGET,
                       help="bytes the fit's largest solve may take; options needing more "
                       f"are refused (default {DEFAULT_MEMORY_BUDGET >> 30}G)")


def _input_limits(args: argparse.Namespace):  # noqa: ANN202 - an InputLimits
    from .fitting.io.limits import InputLimits

    given = {field: getattr(args, field) for _, field, _, _ in INPUT_LIMIT_FLAGS
             if getattr(args, field) is not None}
    return InputLimits(**given)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tessera",
        description="Turn heritage scans into tiny NURBS patches and view them in a browser.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    fit = sub.add_parser(
        "fit",
        help="fit a scan with NURBS patches and write a bundle",
        description="Fit a scan (PLY, OBJ, STL, OFF, GLB/glTF, XYZ/PTS/ASC, .gz, Stanford .conf, "
        "E57, LAS/LAZ) with NURBS patches following Curkovic, Vucina et al.: an atlas of "
        "patches over a whole object, or one patch where one covers it (a relief's point "
        "cloud; with --base patches a relief or a single range scan's mesh too; --patches). "
        "Writes OUTDIR: manifest.json, the base (base.tsa "
        "for an atlas, base.tsp for one patch), detail/ (the zoom levels), error_raster.bin, "
        "error.png and error.ply.",
    )
    fit.add_argument("scan", help="the scan file")
    fit.add_argument("-o", "--output", required=True, help="bundle directory to write")
    add_fit_arguments(fit)
    fit.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    # where the out-of-core passes run (fitter.fitting.stream); not fit options: the bundle
    # is the same bytes, so they stay out of the manifest
    cluster = fit.add_mutually_exclusive_group()
    cluster.add_argument("--workers", type=_count, default=None,
                         help="run the passes over a large scan's points (thinning, error) "
                              "on a Dask LocalCluster of this many worker processes")
    cluster.add_argument("--scheduler", default=None,
                         help="run them on a running Dask scheduler, e.g. tcp://HOST:8786 "
                              "(every worker must see the scan's path)")
    _add_input_limit_arguments(fit)
    fit.set_defaults(run=_cmd_fit)

    tess = sub.add_parser(
        "tessellate",
        help="tessellate a bundle (or a .tsp patch) into a PLY mesh",
        description="Tessellate a bundle at a detail level (an atlas: one welded mesh) or "
        "a .tsp patch into a triangle mesh in the scan's own coordinates and units (the "
        "bundle's stored transform applied; a scan fitted far from the origin stays moved "
        "near it, a header comment giving the origin to add), written as PLY that 3DHOP, "
        "MeshLab and trimesh read: the viewer's Download PLY.",
    )
    tess.add_argument("input", help="a bundle directory (with manifest.json; a folder "
                      "without one: its base.tsp) or a .tsp patch file")
    tess.add_argument("-o", "--output", required=True, help="output .ply path")
    tess.add_argument("--resolution", type=_resolution, default=None,
                      help=f"vertices per side of the parameter grid (default "
                      f"{BASE_RESOLUTION}; a bundle at a detail level L: the level's grid, "
                      "client_py.bundle.plan_level's, at most "
                      f"{PLY_MAX_RESOLUTION}, as the viewer's Download PLY)")
    tess.add_argument("--level", type=_level, default=None,
                      help="with a bundle: apply the detail tiles of levels 0..LEVEL "
                      "(-1: the base alone; default: the finest)")
    tess.add_argument("--texture", action="store_true",
                      help="with a bundle that has texture tiles: write texture_u/v and the "
                      "level's texture as OUTPUT_texture.png instead of vertex colours (an "
                      "atlas: RGB per vertex from its colour packs, as without it)")
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
    serve.add_argument("--production", action="store_true",
                       help="serve with gunicorn, a production WSGI server (pre-forked "
                       "processes), instead of werkzeug's development server")
    serve.add_argument("--processes", type=_count, default=None,
                       help="request processes with --production (default: one per core)")
    serve.add_argument("--threads", type=_count, default=4,
                       help="request threads per process with --production (default 4)")
    serve.add_argument("--fit-workers", type=_count, default=None,
                       help="admin fit jobs run at once (default TESSERA_JOB_WORKERS, "
                       "else one per core)")
    serve.set_defaults(run=_cmd_serve)

    admin = sub.add_parser("admin", help="administer a collection's admin area",
                           description="Administer the admin area of a collection folder.")
    admin_sub = admin.add_subparsers(dest="admin_command", required=True, metavar="ACTION")
    set_token = admin_sub.add_parser(
        "set-token", help="set the admin secret (stored hashed in the collection's catalog)",
        description="Set the secret of the admin area of COLLECTION: read from the terminal "
        "(asked twice), from standard input when piped, or generated with --generate and "
        "printed once. Only a werkzeug password hash is stored, in "
        "COLLECTION/.tessera/catalog.sqlite (made when missing). TESSERA_ADMIN_TOKEN, when "
        "set, takes precedence.")
    set_token.add_argument("collection", help="the collection folder")
    set_token.add_argument("--generate", action="store_true",
                           help="make a random token and print it")
    set_token.set_defaults(run=_cmd_admin_set_token)

    batch = sub.add_parser(
        "fit-collection",
        help="fit many scans in parallel on Dask (a LocalCluster or a cluster's scheduler)",
        description="Fit every SCAN into COLLECTION/<scan name>/ in parallel with Dask "
        "distributed: a LocalCluster of --workers processes by default, or the cluster of "
        "--scheduler. Scans whose bundle is up to date (same input SHA-256 and options) are "
        "skipped; a failed scan does not stop the others; a summary table follows. Exit "
        "status 1 when a scan failed.")
    batch.add_argument("scans", nargs="+", metavar="SCAN", help="scan files")
    batch.add_argument("-o", "--output", required=True, help="the collection folder")
    batch.add_argument("--scheduler", default=None,
                       help="address of a running Dask scheduler, e.g. tcp://HOST:8786")
    batch.add_argument("--workers", type=_count, default=None,
                       help="LocalCluster worker processes (default: one per core)")
    add_fit_arguments(batch, collection=True)
    batch.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    batch.set_defaults(run=_cmd_fit_collection)
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


def console() -> None:
    """The ``tessera`` command: :func:`main`, its process ended by
    :func:`fitter.process_exit.exit_now` (which says why)."""
    exit_now(main())


if __name__ == "__main__":
    console()
