"""Fuzzing client_py's decoders (issue 15): 10^5 hostile inputs of each kind.

``.tsp`` patches and ``.tsd`` tiles as ``client_py.format`` writes them for the fitter,
mutated (bytes flipped, inserted, deleted; the CRC recomputed; claimed sizes enlarged), and
manifests with entries replaced by hostile values (``tests/fuzz_inputs.py``, the generators
the property tests in ``tests/test_fuzz.py`` use). Each input goes through its decoder:
``read_patch``; ``read_detail_tile``; ``plan_levels``, ``detail_nodes``, ``texture_nodes``
and ``WorkerSession.read_manifest`` for a manifest. Counted: inputs accepted, refused with
``PatchFormatError`` and those that raised anything else (outside the contract: must be 0),
the worst time of one input, and the worst peak memory of one input (``tracemalloc``, on
every input over 50 ms and one in 50, since tracing slows every call). An input's time is
its CPU time (``time.process_time``: the shared 2-core machine's other load does not count)
and its wall time, the best of 3 runs for an input over 50 ms (one run of a loaded
machine's scheduler can stall any call). Target: 0 outside the contract, no input over
0.5 s or 256 MB.
``TESSERA_FUZZ_COUNT`` overrides the count per kind (default 100 000).
Writes bench/results/fuzz.json.
"""

from __future__ import annotations

import os
import random
import sys
import time
import tracemalloc
from pathlib import Path

from bench import print_table, write_results

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the generators

COUNT = int(os.environ.get("TESSERA_FUZZ_COUNT", "100000"))
TRACE_EVERY = 50  # one input in 50 is rerun under tracemalloc, and every slow one
SLOW = 0.05  # seconds: an input this slow is rerun (its time: the best of 3) and traced


def _kinds():
    from fuzz_inputs import (
        manifest_text,
        mutate_patch,
        mutate_tile,
        random_manifest,
        seed_manifest,
        seed_patch,
        seed_tiles,
    )

    from client_py.bundle import detail_nodes, plan_levels, texture_nodes
    from client_py.format import read_detail_tile, read_patch
    from client_py.session import WorkerSession

    patch, tiles, manifest = seed_patch(), seed_tiles(), seed_manifest()

    def manifest_calls(m):
        for call in (plan_levels, detail_nodes, texture_nodes):
            yield call, (m,)
        yield WorkerSession().read_manifest, (manifest_text(m),)

    return {
        "tsp": lambda rnd: [(read_patch, (mutate_patch(rnd, patch),))],
        "tsd": lambda rnd: [(read_detail_tile, (mutate_tile(rnd, rnd.choice(tiles)),))],
        "manifest": lambda rnd: list(manifest_calls(random_manifest(rnd, manifest))),
    }


def _run_one(calls) -> str:
    """``'ok'``, ``'refused'`` or the escaping exception's name, over one input's calls."""
    from client_py.errors import PatchFormatError

    outcome = "ok"
    for call, args in calls:
        try:
            call(*args)
        except PatchFormatError:
            outcome = "refused"
        except Exception as exc:  # noqa: BLE001 -- counted: the benchmark's point
            return f"{type(exc).__name__}: {exc}"[:160]
    return outcome


def fuzz(kind: str, make, count: int, seed: int = 15) -> dict:
    rnd = random.Random(seed)
    counts = {"ok": 0, "refused": 0, "outside": 0}
    outside: dict[str, int] = {}
    worst_s, worst_cpu, worst_at, worst_mb = 0.0, 0.0, -1, 0.0
    for k in range(count):
        calls = make(rnd)
        start, cpu = time.perf_counter(), time.process_time()
        outcome = _run_one(calls)
        elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
        if elapsed > SLOW:
            for _ in range(2):
                start = time.perf_counter()
                _run_one(calls)
                elapsed = min(elapsed, time.perf_counter() - start)
        worst_cpu = max(worst_cpu, cpu)
        if elapsed > worst_s:
            worst_s, worst_at = elapsed, k
        if k % TRACE_EVERY == 0 or elapsed > SLOW:
            tracemalloc.start()
            _run_one(calls)
            worst_mb = max(worst_mb, tracemalloc.get_traced_memory()[1] / 1e6)
            tracemalloc.stop()
        if outcome in counts:
            counts[outcome] += 1
        else:
            counts["outside"] += 1
            outside[outcome] = outside.get(outcome, 0) + 1
    return {"kind": kind, "inputs": count, **counts, "worst_s": round(worst_s, 4),
            "worst_cpu_s": round(worst_cpu, 4), "worst_input": worst_at,
            "worst_peak_mb": round(worst_mb, 3),
            "outside_examples": dict(sorted(outside.items(), key=lambda x: -x[1])[:10])}


def run() -> dict:
    rows, results = [], []
    for kind, make in _kinds().items():
        start = time.perf_counter()
        result = fuzz(kind, make, COUNT)
        result["seconds"] = round(time.perf_counter() - start, 1)
        results.append(result)
        rows.append([kind, result["inputs"], result["ok"], result["refused"], result["outside"],
                     f"{result['worst_s'] * 1000:.1f}", f"{result['worst_cpu_s'] * 1000:.1f}",
                     f"{result['worst_peak_mb']:.2f}",
                     result["seconds"]])
    print_table("client_py decoders under fuzzing (target: 0 outside, < 500 ms, < 256 MB)",
                ["input", "count", "decoded", "PatchFormatError", "outside contract",
                 "worst ms", "worst CPU ms", "worst peak MB", "total s"], rows)
    for r in results:
        for name, n in r["outside_examples"].items():
            print(f"  {r['kind']}: {n} x {name}")
    record = {"count_per_kind": COUNT, "results": results,
              "targets": {"outside": 0, "worst_s": 0.5, "worst_peak_mb": 256},
              "load_at_end": os.getloadavg()}
    write_results("fuzz", record)
    return record
