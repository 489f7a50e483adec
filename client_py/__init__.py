"""client_py: Tessera's browser-side Python — NURBS patches in, meshes out.

Runs unchanged in Pyodide and CPython: only the standard library is imported at
import time (numpy, when importable, accelerates grid evaluation behind
``client_py._kernel``); no I/O: bytes in, bytes and arrays out. The browser's
mesh worker drives it through :class:`client_py.session.WorkerSession`.

>>> from client_py import NurbsSurface, tessellate_grid, write_patch, read_patch, write_ply
"""

from .atlas import AtlasSurface
from .atlas_format import read_atlas, write_atlas
from .atlas_mesh import AtlasMesh, atlas_ply, tessellate_atlas
from .basis import uniform_clamped_knots
from .bundle import LevelPlan, plan_level, plan_levels, tessellate_bundle, write_level_ply
from .errors import PatchFormatError, TesseraError
from .format import (
    read_detail_tile,
    read_patch,
    write_detail_tile,
    write_patch,
)
from .layers import DetailTile, TextureImage, tessellate_region
from .ply import write_ply
from .skirts import hang_skirts
from .surface import NurbsSurface
from .tessellate import Mesh, tessellate_grid
from .trim import TrimMask

__all__ = [
    "AtlasMesh",
    "AtlasSurface",
    "DetailTile",
    "LevelPlan",
    "Mesh",
    "NurbsSurface",
    "PatchFormatError",
    "TesseraError",
    "TextureImage",
    "TrimMask",
    "atlas_ply",
    "hang_skirts",
    "plan_level",
    "plan_levels",
    "read_atlas",
    "read_detail_tile",
    "read_patch",
    "tessellate_atlas",
    "tessellate_bundle",
    "tessellate_grid",
    "tessellate_region",
    "uniform_clamped_knots",
    "write_atlas",
    "write_detail_tile",
    "write_level_ply",
    "write_patch",
    "write_ply",
]

__version__ = "0.1.0"
