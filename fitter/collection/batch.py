"""``tessera fit-collection``: many scans fitted in parallel on Dask distributed.

Each scan is one task, ``fit_scan`` on a Dask worker, writing its bundle
``COLLECTION/<name>`` with the pipeline's own atomic rename (temporary folder,
fsync, rename), so a reader of the collection never sees half a bundle.
By default the work runs on a ``LocalCluster`` of ``workers`` single-threaded
worker processes on this machine; with ``scheduler="tcp://HOST:8786"`` it runs
on an existing cluster (``dask scheduler`` and ``dask worker`` as Dask
documents; every worker must see the scan paths and the collection folder,
e.g. on a shared file system).

* A scan whose bundle is up to date is skipped before anything is submitted:
  the existing manifest records the input's SHA-256 (``provenance.sha256``)
  and the options (``options``), and both must equal this run's. The input's
  hash is computed here, streamed, once per scan.
* One failed scan does not stop the others: the task catches the input's
  errors and returns them as its result; a task that dies (a worker lost)
  comes back as a Dask exception and is reported the same way.
* Progress: a bar over scans (tqdm), then a summary table (scan, points,
  bytes, RMS, time, state).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from ..fitting.cores import usable_cores
from ..fitting.options import FitOptions, OptionError, fit_options, stored_options

STATES = ("done", "skipped", "failed")


@dataclass
class ScanResult:
    """The outcome of one scan: ``state`` is one of :data:`STATES`."""

    scan: str
    bundle: str
    state: str
    points: int | None = None
    bytes: int | None = None
    rms: float | None = None
    units: str | None = None
    seconds: float = 0.0
    error: str | None = None


def bundle_name(scan: Path) -> str:
    """The bundle folder of a scan: its name without the format (and ``.gz``) suffixes,
    reduced to an object id's characters (letters, digits, ``.``, ``_``, ``-``)."""
    name = scan.name
    if name.lower().endswith(".gz"):
        name = name[:-3]
    stem = name.rsplit(".", 1)[0] if "." in name else name
    cleaned = re.sub(r"[^A-Za-z0-9._-]+", "-", stem).strip(".-") or "scan"
    return cleaned[:128]


def file_sha256(path: Path, chunk: int = 1 << 20) -> str:
    """SHA-256 of the stored file, streamed (for ``.gz``: of the compressed bytes, as the
    pipeline's provenance records it)."""
    hasher = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            hasher.update(block)
    return hasher.hexdigest()


def is_up_to_date(bundle: Path, sha256: str, options: FitOptions) -> bool:
    """Whether ``bundle`` was fitted from this input (same SHA-256) with these options, and
    its detail tiles (if any) are in the ``.tsd`` version this code reads (of an atlas,
    manifest version 2: its packs' tiles, ``tile_format_version``, and the ``.tsdp`` version
    the code writes: 4, or 5 with walls masks)."""
    from client_py.atlas_detail import PACK_VERSION, WALLS_FREE_VERSION
    from client_py.format import TILE_VERSION

    try:
        manifest = json.loads((bundle / "manifest.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    if not isinstance(manifest, dict):
        return False
    detail = (manifest.get("tiles") or {}).get("detail") or {}
    if manifest.get("format_version") == 2:
        tiles_current = not detail or (detail.get("tile_format_version") == TILE_VERSION
                                       and detail.get("format_version")
                                       in (WALLS_FREE_VERSION, PACK_VERSION))
    else:
        tiles_current = not detail.get("nodes") or detail.get("format_version") == TILE_VERSION
    return (manifest.get("provenance", {}).get("sha256") == sha256
            and manifest.get("options") == stored_options(options) and tiles_current)


def fit_one(scan: str, out_dir: str, options: dict[str, Any]) -> dict[str, Any]:
    """The Dask task: fit one scan; a bad input is a ``failed`` result, not an exception."""
    from ..fitting.io import ScanError
    from ..fitting.pipeline import fit_scan

    start = time.perf_counter()
    result = ScanResult(scan=scan, bundle=out_dir, state="done")
    try:
        bundle = fit_scan(scan, out_dir, fit_options(options))
    except (ScanError, OptionError, OSError) as exc:
        result.state, result.error = "failed", str(exc)
    else:
        m = bundle.manifest
        result.points = m["provenance"]["points"]
        result.bytes = sum(m["files"].values())
        result.rms = m["stats"]["rms"]
        result.units = m.get("units")
    result.seconds = time.perf_counter() - start
    return asdict(result)


def plan(scans: Sequence[str | os.PathLike], out: Path, options: FitOptions
         ) -> tuple[list[tuple[Path, Path]], list[ScanResult]]:
    """Scans to fit ``[(scan, bundle dir)]`` and the up-to-date ones, already skipped.

    Raises
    ------
    ValueError
        Two scans that would write the same bundle folder, or a missing scan.
    """
    todo: list[tuple[Path, Path]] = []
    skipped: list[ScanResult] = []
    names: dict[str, Path] = {}
    for item in scans:
        scan = Path(item)
        if not scan.is_file():
            raise ValueError(f"{scan}: no such scan file")
        name = bundle_name(scan)
        if name in names:
            raise ValueError(f"{names[name]} and {scan} would both write the bundle {name!r}; "
                             "rename one of them")
        names[name] = scan
        bundle = out / name
        if bundle.is_dir() and is_up_to_date(bundle, file_sha256(scan), options):
            manifest = json.loads((bundle / "manifest.json").read_text(encoding="utf-8"))
            skipped.append(ScanResult(str(scan), str(bundle), "skipped",
                                      points=manifest["provenance"].get("points"),
                                      bytes=sum(manifest.get("files", {}).values()),
                                      rms=manifest.get("stats", {}).get("rms"),
                                      units=manifest.get("units")))
        else:
            todo.append((scan, bundle))
    return todo, skipped


def fit_collection(scans: Sequence[str | os.PathLike], out: str | os.PathLike,
                   options: FitOptions | None = None, *, scheduler: str | None = None,
                   workers: int | None = None, processes: bool = True,
                   progress: bool = True, client: Any = None,
                   on_result: Callable[[ScanResult], None] | None = None) -> list[ScanResult]:
    """Fit ``scans`` into the collection folder ``out`` on Dask (see the module docstring).

    Parameters
    ----------
    scans : paths
        Scan files; each becomes ``out/<bundle_name(scan)>``.
    out : path
        The collection folder (created when missing).
    options : FitOptions
        The same options for every scan (validated before anything runs).
    scheduler : str, optional
        Address of a running Dask scheduler; default: a ``LocalCluster``.
    workers : int, optional
        Worker count of the ``LocalCluster`` (default: one per core), each with
        one thread (a fit uses numpy's own threads).
    processes : bool
        ``LocalCluster`` workers as processes (default) or threads in this
        process (quicker to start, for tests).
    progress : bool
        A tqdm bar over scans on stderr.
    client : distributed.Client, optional
        Use this client instead of making one.

    Returns
    -------
    list of ScanResult
        One per scan, in the order given.
    """
    options = options or FitOptions()
    options.grid = tuple(options.grid)
    options.validate()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    todo, skipped = plan(scans, out, options)
    results: dict[str, ScanResult] = {r.scan: r for r in skipped}
    if todo:
        from distributed import Client, LocalCluster, as_completed
        from tqdm import tqdm

        cluster = None
        own_client = client is None
        if client is None:
            if scheduler:
                client = Client(scheduler)
            else:
                n = workers or usable_cores()
                cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=processes,
                                       dashboard_address=None)
                client = Client(cluster)
        record = stored_options(options)
        try:
            futures = {client.submit(fit_one, str(scan), str(bundle), record, pure=False,
                                     key=f"fit-{bundle.name}-{os.urandom(4).hex()}"):
                       (scan, bundle) for scan, bundle in todo}
            bar = tqdm(total=len(todo), desc="scans", unit="scan", file=sys.stderr,
                       disable=not progress)
            for future in as_completed(futures):
                scan, bundle = futures[future]
                try:
                    result = ScanResult(**future.result())
                except Exception as exc:  # noqa: BLE001 - a lost worker or task: report it
                    result = ScanResult(str(scan), str(bundle), "failed",
                                        error=f"{type(exc).__name__}: {exc}")
                results[str(scan)] = result
                if on_result is not None:
                    on_result(result)
                bar.update(1)
            bar.close()
        finally:
            if own_client:
                client.close()
            if cluster is not None:
                cluster.close()
    return [results[str(Path(s))] for s in scans]


def summary_rows(results: Sequence[ScanResult]) -> list[tuple[str, ...]]:
    """Rows of the summary table: scan, points, bytes, RMS, time, state."""
    rows = []
    for r in results:
        rms = "" if r.rms is None else f"{r.rms:.4g}{' ' + r.units if r.units else ''}"
        rows.append((Path(r.scan).name, "" if r.points is None else f"{r.points:,}",
                     "" if r.bytes is None else f"{r.bytes:,}", rms,
                     f"{r.seconds:.1f} s" if r.state != "skipped" else "",
                     r.state if r.error is None else f"{r.state}: {r.error}"))
    return rows


def format_summary(results: Sequence[ScanResult]) -> str:
    headers = ("scan", "points", "bytes", "RMS", "time", "state")
    rows = [headers] + summary_rows(results)
    widths = [max(len(row[k]) for row in rows) for k in range(5)]
    lines = []
    for i, row in enumerate(rows):
        cells = [row[k].rjust(widths[k]) if k in (1, 2, 3, 4) and i else row[k].ljust(widths[k])
                 for k in range(5)]
        lines.append("  ".join(cells + [row[5]]))
        if i == 0:
            lines.append("  ".join("-" * w for w in widths) + "  -----")
    counts = {s: sum(r.state == s for r in results) for s in STATES}
    lines.append(f"{counts['done']} fitted, {counts['skipped']} up to date, "
                 f"{counts['failed']} failed")
    return "\n".join(lines)
