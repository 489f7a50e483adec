"""Tessera's reproducible benchmarks (``make bench`` = ``python -m bench``).

Each benchmark is a module ``bench/bench_<name>.py`` with a ``run()`` function
that measures, prints a table and writes ``bench/results/<name>.json``
(see ``bench/__main__.py`` for the contract). This package holds the small
helpers they share: timing (:func:`best_of`), the machine description every
result file carries (:func:`machine_info`), table printing and JSON output.
Timing targets live here, never in the test suite.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"


def best_of(func: Callable[[], object], repeat: int = 7, warmup: int = 1) -> dict:
    """Seconds of ``func()`` over ``repeat`` runs after ``warmup`` unmeasured ones.

    Returns ``{"best", "median", "runs"}`` in wall-clock time and ``cpu_best``,
    the least process CPU time: the minimum is the figure to compare (least
    disturbed by other load), the median shows the spread, and on a shared
    machine the CPU time shows what waiting for a core added to the wall time.
    """
    for _ in range(warmup):
        func()
    runs, cpu = [], []
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        func()
        runs.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return {"best": min(runs), "median": statistics.median(runs), "cpu_best": min(cpu),
            "runs": runs}


def _command_output(args: Sequence[str]) -> str | None:
    if shutil.which(args[0]) is None:
        return None
    try:
        return subprocess.run(args, capture_output=True, text=True, timeout=30,
                              check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


def machine_info() -> dict:
    """Cores, CPU model, load, OS and the versions of Python, numpy and node."""
    cpu = None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import numpy

        numpy_version = numpy.__version__
    except ImportError:
        numpy_version = None
    return {
        "cores": os.cpu_count(),
        "cpu": cpu or platform.processor() or None,
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "python_implementation": platform.python_implementation(),
        "numpy": numpy_version,
        "node": _command_output(["node", "--version"]),
    }


def write_results(name: str, data: dict) -> Path:
    """Write ``data`` (with ``machine`` and a UTC timestamp added) to ``results/<name>.json``."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    record = {"benchmark": name,
              "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
              "machine": machine_info(), **data}
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    return path


def print_table(title: str, headers: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    """A plain-text table: left-aligned text, right-aligned numbers."""
    cells = [[h for h in headers]] + [[_fmt(c) for c in row] for row in rows]
    widths = [max(len(r[k]) for r in cells) for k in range(len(headers))]
    numeric = [all(isinstance(row[k], int | float) for row in rows) for k in range(len(headers))]

    def line(row):
        return "  ".join(c.rjust(w) if num else c.ljust(w)
                         for c, w, num in zip(row, widths, numeric, strict=True))

    print(f"\n{title}")
    print(line(cells[0]))
    print("  ".join("-" * w for w in widths))
    for row in cells[1:]:
        print(line(row))


def _fmt(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.4f}" if value < 10 else f"{value:.1f}"
    return str(value)
