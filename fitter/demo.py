"""``make demo``: generate the built-in example relief scan and write it as PLY.

Grows with the fitter and the viewer: fit, write the bundle, serve it.
"""

from __future__ import annotations

from pathlib import Path

import trimesh

from .examples import relief_scan


def main() -> None:
    out = Path("demo-out")
    out.mkdir(exist_ok=True)
    scan = out / "example-relief.ply"
    trimesh.PointCloud(relief_scan()).export(scan)
    print(f"wrote the generated example scan {scan}")


if __name__ == "__main__":
    main()
