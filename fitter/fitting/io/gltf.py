"""glTF 2.0 / GLB layout check: refuse a file trimesh would misread, with a message saying why.

trimesh's glTF loader trusts the file: on text that is not JSON it falls back to
asking for a file named ``model.gltf`` (so the error says only ``model.gltf``), and a
``bufferView`` past the end of its buffer trips a bare ``assert``. Before trimesh
sees the bytes, :func:`check_gltf` checks what the loader relies on
(glTF 2.0 specification, sections 3.6 "Binary Data Storage" and 4.4 "GLB File
Format"):

* the container: ``.gltf`` is UTF-8 JSON; ``.glb`` is the 12-byte header (magic
  ``glTF``, version 2, total length) and a first chunk of type ``JSON``, with a
  ``BIN`` chunk after it when buffer 0 has no ``uri``;
* the JSON is an object with ``asset.version`` ``"2.x"``;
* every ``bufferView`` names an existing buffer and lies inside its declared
  ``byteLength``: ``byteOffset + byteLength <= buffer.byteLength``;
* every accessor names an existing ``bufferView``, has a known ``componentType``
  and ``type``, and lies inside the view: with ``s`` the element size
  (components times component bytes) and ``stride`` the view's ``byteStride``
  (default ``s``), ``byteOffset + (count - 1) stride + s <= view.byteLength``.

Whether a buffer's actual data is as long as its declared ``byteLength`` is known
only once trimesh has resolved it (``fitter.fitting.io.mesh`` reports that case).
"""

from __future__ import annotations

import json
import struct
from typing import Any

from client_py.errors import TesseraError

from .scan import ScanError

GLB_MAGIC = b"glTF"
GLB_HEADER = struct.Struct("<4sII")  # magic, version, total length
GLB_CHUNK_HEADER = struct.Struct("<I4s")  # chunk length, chunk type
GLB_JSON_CHUNK = b"JSON"
GLB_BIN_CHUNK = b"BIN\x00"

#: glTF accessor componentType -> bytes per component
COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
#: glTF accessor type -> components per element
TYPE_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9,
                   "MAT4": 16}


def check_gltf(data: bytes, file_type: str, name: str) -> None:
    """Check a ``.gltf`` or ``.glb`` file's container and buffer layout.

    Parameters
    ----------
    data : bytes
        The whole (decompressed) file.
    file_type : {"gltf", "glb"}
        Which container ``data`` is.
    name : str
        File name for the messages.

    Raises
    ------
    ScanError
        ``"NAME: unreadable GLTF content: REASON"`` (or ``GLB``): not JSON or not
        UTF-8, not glTF 2.0, a malformed GLB header or chunk, a missing or malformed
        ``buffers``/``bufferViews``/``accessors`` entry, or a view or accessor
        reaching past what holds it (see the module docstring).
    """
    try:
        _check_layout(data, file_type)
    except _Problem as problem:
        raise ScanError(f"{name}: unreadable {file_type.upper()} content: {problem}") from None


class _Problem(TesseraError):
    """What is wrong with the file (private: :func:`check_gltf` reports it as ScanError)."""


def _check_layout(data: bytes, file_type: str) -> None:
    if file_type == "glb":
        text, bin_length = _glb_json_chunk(data)
    else:
        text, bin_length = data, None
    try:
        tree = json.loads(text.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise _Problem(f"its JSON is not UTF-8 text (byte "
                       f"{exc.start}: {data[exc.start:exc.start + 1]!r})") from None
    except json.JSONDecodeError as exc:
        raise _Problem(f"not JSON ({exc.msg} at line {exc.lineno}, "
                       f"column {exc.colno})") from None
    except RecursionError:
        raise _Problem("its JSON nests too deeply") from None
    if not isinstance(tree, dict):
        raise _Problem(f"the JSON is a {type(tree).__name__}, "
                       "not an object with 'asset', 'buffers', 'meshes' ...")
    _check_version(tree)
    buffers = _entries(tree, "buffers")
    views = _entries(tree, "bufferViews")
    accessors = _entries(tree, "accessors")
    if not buffers and (views or accessors):
        raise _Problem("it has bufferViews or accessors but no 'buffers'")
    lengths = [_count(b, "byteLength", f"buffers[{i}]") for i, b in enumerate(buffers)]
    if bin_length is not None and buffers and "uri" not in buffers[0] \
            and lengths[0] > bin_length:
        raise _Problem(f"buffers[0] declares {lengths[0]} bytes but the GLB's BIN "
                       f"chunk holds {bin_length}")
    for i, view in enumerate(views):
        where = f"bufferViews[{i}]"
        buffer = _index(view, "buffer", len(buffers), where, "buffers")
        start = _count(view, "byteOffset", where, default=0)
        length = _count(view, "byteLength", where)
        if start + length > lengths[buffer]:
            raise _Problem(f"{where} (bytes {start}..{start + length}) overruns "
                           f"buffers[{buffer}], which has {lengths[buffer]} bytes")
    for i, accessor in enumerate(accessors):
        _check_accessor(accessor, i, views)


def _glb_json_chunk(data: bytes) -> tuple[bytes, int | None]:
    """The JSON chunk of a GLB and the length of its BIN chunk (None without one)."""
    if len(data) < GLB_HEADER.size + GLB_CHUNK_HEADER.size:
        raise _Problem(f"not a GLB file: {len(data)} bytes, shorter than the "
                       f"{GLB_HEADER.size + GLB_CHUNK_HEADER.size}-byte header and first chunk")
    magic, version, total = GLB_HEADER.unpack_from(data)
    if magic != GLB_MAGIC:
        raise _Problem(f"not a GLB file: it starts with {magic!r}, not {GLB_MAGIC!r}")
    if version != 2:
        raise _Problem(f"not glTF 2.0: the GLB header states version {version}")
    if total > len(data):
        raise _Problem(f"truncated GLB: the header states {total} bytes, the file "
                       f"has {len(data)}")
    length, kind = GLB_CHUNK_HEADER.unpack_from(data, GLB_HEADER.size)
    start = GLB_HEADER.size + GLB_CHUNK_HEADER.size
    if kind != GLB_JSON_CHUNK:
        raise _Problem(f"not a GLB file: its first chunk is {kind!r}, not "
                       f"{GLB_JSON_CHUNK!r}")
    if start + length > total:
        raise _Problem(f"truncated GLB: the JSON chunk states {length} bytes, "
                       f"{total - start} follow its header")
    text = data[start:start + length]
    rest = start + length
    if rest + GLB_CHUNK_HEADER.size > total:
        return text, None
    bin_length, kind = GLB_CHUNK_HEADER.unpack_from(data, rest)
    if kind != GLB_BIN_CHUNK:
        return text, None
    if rest + GLB_CHUNK_HEADER.size + bin_length > total:
        raise _Problem(f"truncated GLB: the BIN chunk states {bin_length} bytes, "
                       f"{total - rest - GLB_CHUNK_HEADER.size} follow its header")
    return text, bin_length


def _check_version(tree: dict) -> None:
    asset = tree.get("asset")
    version = asset.get("version") if isinstance(asset, dict) else None
    if not isinstance(version, str):
        raise _Problem(f"not glTF 2.0: no 'asset': {{'version': '2.0'}} "
                       f"(found asset {asset!r:.60})")
    if version.split(".", 1)[0] != "2":
        raise _Problem(f"not glTF 2.0: asset.version is {version!r:.20} (only 2.x "
                       "is read)")


def _entries(tree: dict, key: str) -> list[dict]:
    value = tree.get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        raise _Problem(f"glTF {key!r} must be a list of objects, got {value!r:.60}")
    return value


def _count(entry: dict, key: str, where: str, default: int | None = None) -> int:
    value = entry.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        shown = "missing" if value is None else repr(value)
        raise _Problem(f"{where}.{key} must be an integer >= 0, got {shown:.40}")
    return value


def _index(entry: dict, key: str, n: int, where: str, target: str) -> int:
    value = _count(entry, key, where)
    if value >= n:
        raise _Problem(f"{where}.{key} is {value}, but there are {n} {target}")
    return value


def _check_accessor(accessor: dict, i: int, views: list[dict]) -> None:
    where = f"accessors[{i}]"
    component = accessor.get("componentType")
    kind = accessor.get("type")
    if not isinstance(component, int) or isinstance(component, bool) \
            or component not in COMPONENT_BYTES:
        raise _Problem(f"{where}.componentType is {component!r:.20}; glTF 2.0 "
                       f"accepts {', '.join(map(str, COMPONENT_BYTES))}")
    if not isinstance(kind, str) or kind not in TYPE_COMPONENTS:
        raise _Problem(f"{where}.type is {kind!r:.20}; glTF 2.0 accepts "
                       f"{', '.join(TYPE_COMPONENTS)}")
    count = _count(accessor, "count", where)
    if "bufferView" not in accessor:
        return  # all zeros (or sparse values) by the specification: nothing to overrun
    view_index = _index(accessor, "bufferView", len(views), where, "bufferViews")
    view: dict[str, Any] = views[view_index]
    element = COMPONENT_BYTES[component] * TYPE_COMPONENTS[kind]
    stride = _count(view, "byteStride", f"bufferViews[{view_index}]", default=element)
    if stride == 0:
        raise _Problem(f"bufferViews[{view_index}].byteStride is 0 (must be >= 1)")
    start = _count(accessor, "byteOffset", where, default=0)
    end = start + (count - 1) * stride + element if count else start
    if end > view["byteLength"]:
        raise _Problem(f"{where} ({count} x {kind} of {element} bytes from byte "
                       f"{start}, stride {stride}: bytes {start}..{end}) overruns "
                       f"bufferViews[{view_index}], which has {view['byteLength']} bytes")
