"""``make demo``: fit the built-in examples and serve the viewer.

Generates the two synthetic examples of ``fitter.fitting.examples`` (labelled as
generated in their titles): the carved relief (``relief_scan``, a point cloud, fitted
as one patch) and the fluted vase (``vase_mesh``, a closed mesh, fitted as an atlas of
patches over the whole object), writes each as a PLY file like a scanner's, fits them
with ``tessera fit`` defaults into ``demo-out/collection/``, prints the fit summaries and
serves the collection at the printed URL.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from client_py.ply import write_points_ply

from .fitting.examples import relief_scan, vase_mesh
from .process_exit import exit_now


def write_scan_ply(path: Path, points: np.ndarray) -> None:
    """A binary point-cloud PLY of ``points (N, 3)`` (float32 ``x y z``) with a units
    comment, as scanner software writes (by :func:`client_py.ply.write_points_ply`)."""
    data = write_points_ply(np.ascontiguousarray(points, dtype=np.float32),
                            comments=["units mm",
                                      "generated example relief (synthetic, not a real scan)"])
    Path(path).write_bytes(data)


def write_mesh_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A binary triangle-mesh PLY (``x y z`` and ``vertex_indices``), as a scanner's
    reconstruction software writes one (by trimesh)."""
    import trimesh

    trimesh.Trimesh(vertices, faces, process=False).export(path, file_type="ply")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Fit the built-in examples and serve them.")
    parser.add_argument("--out", default="demo-out", help="working folder (default demo-out)")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", default="8000")
    parser.add_argument("--no-serve", action="store_true", help="fit only")
    args = parser.parse_args(argv)
    from .cli import main as tessera

    out = Path(args.out)
    (out / "scans").mkdir(parents=True, exist_ok=True)
    (out / "collection").mkdir(parents=True, exist_ok=True)
    scan = out / "scans" / "example-relief.ply"
    write_scan_ply(scan, relief_scan())
    print(f"generated the example scan {scan} (synthetic carved relief, 80,000 points)")
    status = tessera(["fit", str(scan), "-o", str(out / "collection" / "example-relief"),
                      "--title", "Example relief (generated)"])
    if status:
        return status
    vase = out / "scans" / "example-vase.ply"
    vertices, faces = vase_mesh()
    write_mesh_ply(vase, vertices, faces)
    print(f"generated the example scan {vase} (synthetic fluted vase, a closed mesh of "
          f"{len(faces):,} triangles)")
    status = tessera(["fit", str(vase), "-o", str(out / "collection" / "example-vase"),
                      "--units", "mm", "--title", "Example vase (generated)"])
    if status or args.no_serve:
        return status
    return tessera(["serve", str(out / "collection"), "--host", args.host, "--port", args.port])


if __name__ == "__main__":
    exit_now(main())
