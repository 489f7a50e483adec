"""Run Tessera's benchmarks: ``python -m bench [NAME ...]`` (``make bench`` runs them all).

Adding a benchmark
------------------
Create ``bench/bench_<name>.py`` with a function ``run() -> dict | None`` that

1. measures (use :func:`bench.best_of` for timings: best and median of repeats),
2. prints one or more tables (:func:`bench.print_table`), and
3. writes its numbers with :func:`bench.write_results` to ``bench/results/<name>.json``
   (which adds the machine description: cores, CPU, load, Python/numpy/node versions).

It is found by its file name, no registration needed; it returns its result
record (or None). A benchmark that takes options defines ``add_arguments(parser)``
(an ``argparse`` parser of its own) and ``run(**options)`` receives them. A benchmark
that cannot run here (a missing tool) prints why and returns None rather than failing
the others. Keep each one to a minute or
two on the 2-core reference machine.

Usage
-----
``python -m bench``               every ``bench_*.py`` module, in name order
``python -m bench tessellate``    only ``bench_tessellate.py``
``python -m bench --list``        the names found
``python -m bench fit --points 1e8``  one benchmark with its own options
                                  (``python -m bench fit -h`` lists them)
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import time
import traceback
from pathlib import Path

from fitter.process_exit import exit_now

PACKAGE_DIR = Path(__file__).resolve().parent


def available() -> list[str]:
    """Names ``<name>`` of the ``bench/bench_<name>.py`` modules, sorted."""
    return sorted(m.name[len("bench_"):] for m in pkgutil.iter_modules([str(PACKAGE_DIR)])
                  if m.name.startswith("bench_"))


def _benchmark_options(parser: argparse.ArgumentParser, name: str,
                       argv: list[str]) -> dict:
    """The options ``argv`` of benchmark ``name``, parsed by the parser its module's
    ``add_arguments(parser)`` builds."""
    module = importlib.import_module(f"bench.bench_{name}")
    if not hasattr(module, "add_arguments"):
        parser.error(f"bench {name} takes no options (given: {' '.join(argv)})")
    summary = " ".join((module.__doc__ or "").split("\n\n")[0].split())  # first paragraph
    own = argparse.ArgumentParser(prog=f"python -m bench {name}", description=summary)
    module.add_arguments(own)
    return vars(own.parse_args(argv))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.split("\n")[0])
    parser.add_argument("names", nargs="*", help="benchmarks to run (default: all)")
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    argv = list(sys.argv[1:] if argv is None else argv)
    # NAME --option ...: the options after a benchmark's name are that benchmark's own
    first_option = next((i for i, a in enumerate(argv) if a.startswith("-")), len(argv))
    own_options = argv[first_option:] if first_option > 0 else []
    args = parser.parse_args(argv[:first_option] if own_options else argv)
    names = available()
    if args.list:
        print("\n".join(names))
        return 0
    unknown = [n for n in args.names if n not in names]
    if unknown:
        parser.error(f"unknown benchmark(s) {', '.join(unknown)}; available: {', '.join(names)}")
    options = {}
    if own_options:
        if len(args.names) != 1:
            parser.error("options after the names belong to one benchmark: name only that one "
                         f"(got {', '.join(args.names)})")
        options = _benchmark_options(parser, args.names[0], own_options)
    failed = []
    for name in args.names or names:
        print(f"=== bench {name} ===", flush=True)
        start = time.perf_counter()
        try:
            importlib.import_module(f"bench.bench_{name}").run(**options)
        except Exception:  # noqa: BLE001 - report and go on with the other benchmarks
            traceback.print_exc()
            failed.append(name)
        print(f"=== {name}: {time.perf_counter() - start:.1f} s ===\n", flush=True)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    exit_now(main())
