"""Mesh formats through trimesh: OBJ (with its MTL and texture), STL, OFF, glTF/GLB, and PLY meshes.

The file is read once through ``HashedInput`` (so ``.gz`` works and the
SHA-256 is taken on the way) and handed to trimesh's format loader
(``trimesh.exchange.load.mesh_loaders``) as bytes. The loader's keyword
dictionaries are used directly rather than ``trimesh.Trimesh`` objects: they
say exactly which arrays the file had (a ``Trimesh`` would invent vertex
normals on request) and nothing is merged or reordered (``process=False``
semantics). Scenes (glTF nodes, OBJ objects) are flattened here by composing
the scene graph's 4x4 transforms, ``p_world = M_root ... M_node p``; normals
go through the inverse transpose of the linear part.

Companion files (OBJ's ``.mtl`` and texture, glTF's ``.bin`` and images) are
fetched by trimesh through ``_HashingResolver``, which records each file's size
and SHA-256 in ``source["files"]``, and a missing one in ``source["warnings"]``.
STL stores three vertices per triangle; exact duplicates are merged (first
occurrence order) so the points are the surface's vertices, not a triple copy.

Text formats (OBJ and its MTL, OFF, ASCII STL) are read as UTF-8 and, when they
are not UTF-8, as Latin-1: their keywords and numbers are ASCII, so only names and
comments can hold other bytes, and Latin-1 maps every byte to a character. The
text goes to trimesh re-encoded as UTF-8 (trimesh would otherwise guess the
encoding with ``charset_normalizer``, which is not a dependency: one fewer
package, and no guess). A cp1252 name comes out as its Latin-1 reading, which
differs only in bytes 0x80-0x9F; the source's warnings say so.

Every failure is a ``ScanError`` naming the file and the problem: glTF/GLB layout
is checked first by ``fitter.fitting.io.gltf``; what trimesh's loaders raise on
corrupt content (listed in ``TRIMESH_ERRORS``, read from trimesh's source) is
reported with its reason.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path
from typing import Any

import numpy as np

from .gltf import check_gltf
from .limits import InputBudget
from .scan import Scan, ScanError, colors_to_uint8, make_scan, new_source, units_from_comments
from .source import GZIP_ERRORS, HashedInput, file_record

#: what trimesh's loaders raise on corrupt input (caught and reported as ScanError):
#: numpy and parsing errors throughout; ``AssertionError`` from the glTF reader's layout
#: asserts (``exchange/gltf``: a view longer than its buffer's actual data); ``NameError``
#: from the OFF reader's header check (``exchange/off.py``); ``OSError`` from the resolver
#: (a companion file missing or unreadable)
TRIMESH_ERRORS = (ValueError, IndexError, KeyError, TypeError, AttributeError, struct.error,
                  UnicodeDecodeError, OverflowError, NotImplementedError, AssertionError,
                  NameError, OSError, *GZIP_ERRORS)
#: what turning trimesh's output (lists or arrays of any shape) into ours raises
ARRAY_ERRORS = (ValueError, TypeError, IndexError, KeyError, AttributeError,
                np.linalg.LinAlgError)
#: formats trimesh reads as text (STL only when it is ASCII: ``_check_stl``)
TEXT_FORMATS = ("obj", "off", "stl")
#: companion files that are text (re-encoded like the main file)
TEXT_COMPANIONS = (".mtl",)


def text_as_utf8(data: bytes) -> tuple[bytes, bool]:
    """``(data as UTF-8, whether it was re-read as Latin-1)``: UTF-8 text unchanged,
    anything else decoded as Latin-1 and re-encoded (see the module docstring)."""
    try:
        data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("latin-1").encode("utf-8"), True
    return data, False


def obj_header_comments(data: bytes, limit: int = 200) -> list[str]:
    """The ``#`` comment lines that open an OBJ file (before its first statement, at most
    ``limit``), without the ``#``: where a ``# units mm`` line is looked for."""
    comments = []
    for line in data[:1 << 16].splitlines()[:limit]:
        text = line.strip()
        if text and not text.startswith(b"#"):
            break
        if text:
            comments.append(text[1:].decode("utf-8", "replace"))
    return comments


def _hashing_resolver(path: Path, records: list[dict], missing: list[str],
                      warnings: list[str]) -> Any:
    from trimesh.resolvers import FilePathResolver

    folder = path.resolve().parent

    class _HashingResolver(FilePathResolver):
        """A trimesh resolver that records every companion file it hands out, confined
        to the scan's folder (trimesh < 5 would follow ``../`` and absolute names)."""

        def get(self, name: str) -> bytes:
            if not (folder / name.strip()).resolve().is_relative_to(folder):
                missing.append(name)
                raise ValueError(f"companion file {name!r} is outside the scan's folder")
            try:
                data = super().get(name)
            except (OSError, ValueError):
                missing.append(name)
                raise
            if not any(r["name"] == name for r in records):
                records.append(file_record(name, data, role="companion"))
            if name.lower().endswith(TEXT_COMPANIONS):
                data, recoded = text_as_utf8(data)
                if recoded:
                    warnings.append(f"companion file {name!r} is not UTF-8: read as Latin-1")
            return data

    return _HashingResolver(str(path))


def load_mesh(path: Path, gzipped: bool, budget: InputBudget | None = None, *,
              file_type: str) -> Scan:
    """Read an OBJ, STL, OFF, glTF or GLB file (optionally ``.gz``) through trimesh;
    ``budget`` (``fitter.fitting.io.limits``) bounds the gzip stream."""
    with HashedInput(path, gzipped, budget) as inp:
        try:
            data = inp.stream.read()
        except GZIP_ERRORS as exc:
            raise ScanError(f"{path.name}: corrupt gzip data: {exc}") from None
        record = inp.finish()
    units = ("m" if file_type in ("gltf", "glb")  # glTF 2.0 spec: metres
             else units_from_comments(obj_header_comments(data)) if file_type == "obj"
             else "unknown")
    return scan_from_trimesh(path, file_type, data, record, gzipped, units=units)


def scan_from_trimesh(path: Path, file_type: str, data: bytes, record: dict, gzipped: bool,
                      units: str = "unknown", extra_source: dict | None = None) -> Scan:
    """Parse ``data`` (the whole decompressed file) with trimesh's loader for ``file_type``."""
    name = path.name
    if file_type == "stl":  # checks of our own first: a bad file is refused before the import
        _check_stl(data, name)
    if file_type in ("gltf", "glb"):
        check_gltf(data, file_type, name)
    from trimesh.exchange.load import mesh_loaders

    records: list[dict] = [record]
    missing: list[str] = []
    warnings: list[str] = []
    resolver = _hashing_resolver(path, records, missing, warnings)
    if file_type in TEXT_FORMATS and not _is_binary_stl(data):
        data, recoded = text_as_utf8(data)
        if recoded:
            warnings.append(f"{name} is not UTF-8: read as Latin-1")
    loader = mesh_loaders[file_type]
    try:
        kwargs = loader(file_obj=io.BytesIO(data), file_type=file_type, resolver=resolver)
    except TRIMESH_ERRORS as exc:
        raise ScanError(_loader_failure(name, file_type, exc, missing)) from None
    source = new_source(name, str(path), file_type, "gzip" if gzipped else None, "trimesh")
    source.update(bytes=record["bytes"], sha256=record["sha256"], files=records,
                  hash_method="sha256 of each file as stored, computed on the single read",
                  **(extra_source or {}))
    source["warnings"] += warnings
    source["warnings"] += [f"companion file {m!r} not found" for m in dict.fromkeys(missing)]
    try:
        arrays = _combine(_flatten(kwargs), source["warnings"], name)
    except ScanError:
        raise
    except ARRAY_ERRORS as exc:  # e.g. ragged vertex rows from a cut-short ASCII PLY
        raise ScanError(f"{name}: unusable {file_type.upper()} content: the geometry read "
                        f"does not form arrays of points and triangles ({type(exc).__name__}: "
                        f"{exc})") from None
    if file_type == "stl" and arrays["faces"] is not None:
        arrays["points"], arrays["faces"] = _merge_duplicates(arrays["points"], arrays["faces"])
    return make_scan(name, arrays["points"], normals=arrays["normals"], colors=arrays["colors"],
                     faces=arrays["faces"], uv=arrays["uv"], texture=arrays["texture"],
                     units=units, source=source)


def _loader_failure(name: str, file_type: str, exc: Exception, missing: list[str]) -> str:
    """The message of a trimesh loader's failure: what is wrong, in our words where we can."""
    kind = file_type.upper()
    if missing and missing[-1] in str(exc):
        return (f"{name}: cannot read its companion file {missing[-1]!r} (missing, unreadable "
                f"or outside the scan's folder: {exc})")
    if isinstance(exc, AssertionError):  # the glTF reader's asserts, after check_gltf
        return (f"{name}: inconsistent {kind} layout: a bufferView or accessor reaches past "
                "the data its buffer actually holds (shorter than its byteLength)")
    detail = str(exc) or "no detail given"
    return f"{name}: unreadable {kind} content ({type(exc).__name__}: {detail:.300})"


def _is_binary_stl(data: bytes) -> bool:
    """84 + 50 n bytes for the n triangles its header states."""
    return len(data) >= 84 and len(data) == 84 + 50 * struct.unpack("<I", data[80:84])[0]


def _check_stl(data: bytes, name: str) -> None:
    """A binary STL is 84 + 50 n bytes for the n its header states; else it must be ASCII."""
    if _is_binary_stl(data):
        return
    n = struct.unpack("<I", data[80:84])[0] if len(data) >= 84 else 0
    if data[:5].lower() == b"solid" and b"facet" in data[:4096].lower():
        return
    stated = f"its header states {n} triangles = {84 + 50 * n} bytes, " if len(data) >= 84 else ""
    raise ScanError(f"{name}: corrupt or truncated STL: {stated}the file has {len(data)} bytes, "
                    "and it is not ASCII STL ('solid ... facet ...') either")


def _flatten(kwargs: dict) -> list[tuple[dict, np.ndarray]]:
    """``[(geometry kwargs, 4x4 world matrix)]`` from a mesh or scene keyword dict."""
    if "geometry" not in kwargs:
        return [(kwargs, np.eye(4))]
    geometry = kwargs["geometry"]
    graph = kwargs.get("graph") or []
    if not graph:
        return [(g, np.eye(4)) for g in geometry.values()]
    base = kwargs.get("base_frame", "world")

    def frame(edge: dict) -> str:
        return edge.get("frame_to", edge.get("geometry"))

    parent = {frame(e): (e.get("frame_from", base), np.asarray(e.get("matrix", np.eye(4)), float))
              for e in graph}

    def world(frame: str, depth: int = 0) -> np.ndarray:
        if frame not in parent or depth > len(parent):
            return np.eye(4)
        up, matrix = parent[frame]
        return world(up, depth + 1) @ matrix

    return [(geometry[e["geometry"]], world(frame(e)))
            for e in graph if e.get("geometry") in geometry]


def _texture_of(visual: Any) -> tuple[np.ndarray | None, Any]:
    """``(uv, image)`` of a trimesh TextureVisuals (Simple or PBR material), else Nones."""
    if visual is None or getattr(visual, "kind", None) != "texture":
        return None, None
    uv = getattr(visual, "uv", None)
    material = getattr(visual, "material", None)
    image = getattr(material, "image", None)
    if image is None:
        image = getattr(material, "baseColorTexture", None)
    return (None if uv is None else np.asarray(uv, np.float64)), image


def _colors_of(geom: dict) -> np.ndarray | None:
    colors = geom.get("vertex_colors")
    visual = geom.get("visual")
    if colors is None and visual is not None:
        if getattr(visual, "kind", None) == "vertex":
            colors = visual.vertex_colors
        elif getattr(visual, "kind", None) == "texture":
            colors = getattr(visual, "vertex_attributes", {}).get("color")
    if colors is None:
        return None
    colors = np.asarray(colors)
    return colors_to_uint8(colors) if colors.ndim == 2 and colors.shape[1] >= 3 else None


def _combine(parts: list[tuple[dict, np.ndarray]], warnings: list[str], name: str) -> dict:
    """Concatenate the geometries of a scene, transformed into its root frame."""
    points, faces, normals, colors, uvs, images = [], [], [], [], [], []
    offset = 0
    for geom, matrix in parts:
        if "entities" in geom:
            warnings.append("a path/line geometry was skipped (not a surface)")
            continue
        vertices = np.asarray(geom.get("vertices", np.empty((0, 3))), np.float64).reshape(-1, 3)
        if not np.allclose(matrix, np.eye(4)):
            vertices = vertices @ matrix[:3, :3].T + matrix[:3, 3]
        points.append(vertices)
        if geom.get("faces") is not None and len(geom["faces"]):
            f = np.asarray(geom["faces"], np.int64)
            if f.ndim != 2 or f.shape[1] != 3:
                raise ScanError(f"{name}: faces are not triangles (shape {f.shape})")
            faces.append(f + offset)
        n = geom.get("vertex_normals")
        if n is not None:
            n = np.asarray(n, np.float64).reshape(-1, 3)
            if not np.allclose(matrix, np.eye(4)):
                n = n @ np.linalg.inv(matrix[:3, :3])
                n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        normals.append(n)
        colors.append(_colors_of(geom))
        uv, image = _texture_of(geom.get("visual"))
        uvs.append(uv)
        images.append(image)
        offset += len(vertices)
    if not points:
        raise ScanError(f"{name}: the file contains no points")

    def joined(arrays: list) -> np.ndarray | None:
        return np.concatenate(arrays) if all(a is not None for a in arrays) else None

    texture = images[0] if images and all(i is images[0] for i in images) else None
    if texture is None and any(i is not None for i in images):
        warnings.append("several texture images: textures and uv were not kept")
    uv = joined(uvs) if texture is not None else None
    if any(u is not None for u in uvs) and texture is None and uv is None:
        if all(i is None for i in images):
            warnings.append("texture coordinates without a texture image were not kept")
    return {"points": np.concatenate(points), "faces": np.concatenate(faces) if faces else None,
            "normals": joined(normals), "colors": joined(colors), "uv": uv, "texture": texture}


def _merge_duplicates(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical vertices (STL's per-triangle copies), keeping first-occurrence order."""
    _, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # unique rows sorted by where they first appear
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return points[first[order]], rank[inverse.reshape(-1)][faces]
