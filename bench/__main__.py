"""Run Tessera's benchmarks: ``python -m bench [NAME ...]`` (``make bench`` runs them all).

Adding a benchmark
------------------
Create ``bench/bench_<name>.py`` with a function ``run() -> dict | None`` that

1. measures (use :func:`bench.best_of` for timings: best and median of repeats),
2. prints one or more tables (:func:`bench.print_table`), and
3. writes its numbers with :func:`bench.write_results` to ``bench/results/<name>.json``
   (which adds the machine description: cores, CPU, load, Python/numpy/node versions).

It is found by its file name, no registration needed; it returns its result
record (or None). A benchmark that cannot run here (a missing tool) prints why
and returns None rather than failing the others. Keep each one to a minute or
two on the 2-core reference machine.

Usage
-----
``python -m bench``               every ``bench_*.py`` module, in name order
``python -m bench tessellate``    only ``bench_tessellate.py``
``python -m bench --list``        the names found
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import time
import traceback
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent


def available() -> list[str]:
    """Names ``<name>`` of the ``bench/bench_<name>.py`` modules, sorted."""
    return sorted(m.name[len("bench_"):] for m in pkgutil.iter_modules([str(PACKAGE_DIR)])
                  if m.name.startswith("bench_"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.split("\n")[0])
    parser.add_argument("names", nargs="*", help="benchmarks to run (default: all)")
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    args = parser.parse_args(argv)
    names = available()
    if args.list:
        print("\n".join(names))
        return 0
    unknown = [n for n in args.names if n not in names]
    if unknown:
        parser.error(f"unknown benchmark(s) {', '.join(unknown)}; available: {', '.join(names)}")
    failed = []
    for name in args.names or names:
        print(f"=== bench {name} ===", flush=True)
        start = time.perf_counter()
        try:
            importlib.import_module(f"bench.bench_{name}").run()
        except Exception:  # noqa: BLE001 - report and go on with the other benchmarks
            traceback.print_exc()
            failed.append(name)
        print(f"=== {name}: {time.perf_counter() - start:.1f} s ===\n", flush=True)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
