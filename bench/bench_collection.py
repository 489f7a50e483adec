"""Batch-fit benchmark (issue 7): ``fit-collection`` of 8 generated scans on 1 and 2 Dask
workers.

Eight generated reliefs (seeds 0-7, 40,000 points each, synthetic), saved as binary PLY,
are fitted with Tessera's default method on a 24x24 grid by
:func:`fitter.collection.batch.fit_collection` on a ``LocalCluster`` of 1, then 2
single-threaded worker processes, into a fresh collection each time. The wall time of
the fits is measured with the cluster already running (its start-up is reported apart);
the speed-up is 1-worker time / 2-worker time. Each fit pins BLAS to one thread (the
pipeline does), so two workers can use the two cores. Writes
bench/results/collection.json.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from bench import print_table, write_results

N_SCANS = 8
N_POINTS = 40_000
GRID = (24, 24)


def run() -> dict:
    from distributed import Client, LocalCluster

    from fitter.collection.batch import fit_collection
    from fitter.demo import write_scan_ply
    from fitter.fitting.examples import relief_scan
    from fitter.fitting.options import FitOptions

    rows, records = [], []
    with tempfile.TemporaryDirectory() as tmp:
        scans = []
        for seed in range(N_SCANS):
            path = Path(tmp) / f"relief-{seed}.ply"
            write_scan_ply(path, relief_scan(N_POINTS, seed=seed))
            scans.append(path)
        for workers in (1, 2):
            start = time.perf_counter()
            with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                              dashboard_address=None) as cluster, Client(cluster) as client:
                startup = time.perf_counter() - start
                # a warm-up task imports the fitter on every worker (not part of the fits)
                client.run(lambda: __import__("fitter.fitting.pipeline"))
                start = time.perf_counter()
                results = fit_collection(scans, Path(tmp) / f"out-{workers}",
                                         FitOptions(grid=GRID), client=client, progress=False)
                wall = time.perf_counter() - start
            states = sorted({r.state for r in results})
            records.append({"workers": workers, "wall_s": wall, "cluster_startup_s": startup,
                            "scan_seconds": [r.seconds for r in results], "states": states})
            rows.append((workers, round(wall, 2), round(sum(r.seconds for r in results), 2),
                         round(startup, 2), ",".join(states)))
    speedup = records[0]["wall_s"] / records[1]["wall_s"]
    print_table(f"fit-collection: {N_SCANS} generated scans x {N_POINTS:,} points, "
                f"{GRID[0]}x{GRID[1]} tessera, LocalCluster (speed-up 2 vs 1 worker: "
                f"{speedup:.2f}x)",
                ["workers", "wall s", "sum of fits s", "cluster start s", "states"], rows)
    data = {"scans": N_SCANS, "points": N_POINTS, "grid": list(GRID), "method": "tessera",
            "runs": records, "speedup_2_vs_1": speedup}
    write_results("collection", data)
    return data


if __name__ == "__main__":
    run()
