"""Checking a received scan upload: identified by its content, archives checked.

The server streams the multipart body to disk (``fitter.server.admin.upload_stream``)
and hands the file over as a :class:`ReceivedFile`. :func:`prepare_scan` then
decides what the bytes are:

* the format is sniffed from the content (:func:`sniff_format`: PLY, OBJ, STL,
  OFF, glTF/GLB, XYZ/PTS/ASC text clouds, E57 by its ``ASTM-E57`` signature, LAS/LAZ by
  ``LASF`` and the LASzip bit of the point format); the client's file name is kept as
  metadata only, and the stored file gets a generated name (``scan.ply``), so
  no part of a client's name ever reaches the file system;
* a gzip stream (``.gz``) is decompressed once, to a counter, with an absolute
  size limit and a compression-ratio limit (a decompression bomb stops within
  one chunk of the limit: the same counter, ``fitter.fitting.io.source.BoundedReader``,
  as every scan read); its content is sniffed from the decompressed head
  and the file is kept compressed (``fitter.fitting.io`` reads ``.gz`` itself);
* a zip archive has every member checked before anything is written (absolute
  names, ``..`` components, drive letters, symbolic links, member count,
  declared sizes and ratios), then is extracted with the sizes counted again
  on the real bytes (declared sizes can lie); it must hold exactly one scan
  (or one Stanford ``.conf`` with its range scans), OBJ materials and textures
  beside it; a ``.conf`` has every line checked as the fit will read it
  (``fitter.fitting.io.conf.check_registration``: each named file inside the
  ``.conf``'s folder, named once, at most ``max_files``) and every ``.gz`` it names
  decompressed to the counter, with all of them counting towards one
  ``max_expanded_bytes``.

The limits are :class:`UploadLimits`: the fitting library's one
``fitter.fitting.io.limits.InputLimits`` (decompressed bytes, ratio, points, files per
registration), spelled with the server's ``TESSERA_UPLOAD_*`` settings, plus the request
size and the zip's member count.

Every refusal is an :class:`UploadError` carrying the HTTP status (400 or 413)
and a message that says what is wrong.
"""

from __future__ import annotations

import gzip
import os
import re
import shutil
import stat
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from client_py.errors import TesseraError

from ..fitting.io import NOT_GZIPPED, SUPPORTED_EXTENSIONS
from ..fitting.io.conf import check_registration, read_conf
from ..fitting.io.limits import InputBudget, InputLimits
from ..fitting.io.scan import ScanError
from ..fitting.io.source import (
    GZIP_READ_BYTES,
    BoundedReader,
    HashingReader,
    declared_gzip_size,
)

CHUNK = 1 << 20
SNIFF_BYTES = 1 << 16
#: the names a stored upload may have (all generated here)
STORED_NAME = re.compile(r"^scan\.[a-z0-9]+(\.gz)?$|^upload\.zip$")


class UploadError(TesseraError, ValueError):
    """An upload refused: ``status`` is the HTTP status to answer (400 or 413)."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class UploadLimits(InputLimits):
    """Limits of one upload: the scan read's ``InputLimits`` (whose refusals name the
    ``TESSERA_UPLOAD_*`` settings) and two of the upload itself.

    max_bytes : the request body (default 4 GiB); max_expanded_bytes : the
    decompressed size of a ``.gz``, of all a zip's members, or of all the ``.gz`` a
    ``.conf`` names (default 16 GiB); max_ratio : decompressed / compressed size
    (default 200, far above real scans: binary PLY compresses 2-4x, ASCII clouds 5-10x);
    max_points, max_files : as ``InputLimits``; max_members : zip members (default 1000).
    """

    max_expanded_bytes: int = 16 << 30
    context: str = "upload"
    max_bytes: int = 4 << 30
    max_members: int = 1000


@dataclass
class ReceivedFile:
    """The file part of an upload as written to disk."""

    path: Path
    original_name: str
    bytes: int
    sha256: str


@dataclass
class PreparedScan:
    """An accepted upload: the file ``fitter.fitting.io.load_scan`` will read."""

    scan_path: Path
    format: str
    compression: str | None
    notes: list[str] = field(default_factory=list)


def format_size(nbytes: float) -> str:
    """``nbytes`` for a message: ``"512 bytes"``, ``"3.5 MiB"``."""
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if nbytes < 1024 or unit == "GiB":
            return f"{nbytes:.0f} {unit}" if unit == "bytes" else f"{nbytes:.1f} {unit}"
        nbytes /= 1024
    return f"{nbytes} bytes"


# ----------------------------------------------------------------------------- sniffing
_NUMBER = re.compile(rb"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")
_OFF_KEYWORDS = {b"OFF", b"COFF", b"NOFF", b"CNOFF", b"STOFF", b"4OFF", b"NCOFF"}
TEXT_CLOUDS = (".xyz", ".pts", ".asc")


def _text_lines(head: bytes) -> list[bytes] | None:
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:  # not just a character cut at the end of the head
            return None
    if b"\x00" in head:
        return None
    lines = head.splitlines()
    if len(head) == SNIFF_BYTES and lines:
        lines = lines[:-1]  # the last line may be cut
    return [ln.strip() for ln in lines if ln.strip() and not ln.lstrip().startswith(b"#")]


def sniff_format(head: bytes, total_size: int | None = None, name_hint: str = "") -> str | None:
    """The scan format of a file from its first bytes: an extension of
    :data:`fitter.fitting.io.SUPPORTED_EXTENSIONS` (without ``.conf``), or None.

    ``total_size`` lets a binary STL be recognised by its triangle count
    (``84 + 50 n`` bytes); ``name_hint`` (the client's file name) only chooses
    among ``.xyz``, ``.pts`` and ``.asc``, which are the same kind of content.
    """
    if head.startswith((b"ply\n", b"ply\r\n")):
        return ".ply"
    if head.startswith(b"ASTM-E57"):  # the E57 file header's signature (ASTM E2807)
        return ".e57"
    if head.startswith(b"LASF"):
        # the point data format byte (offset 104): LASzip sets bit 7 (and not bit 6)
        compressed = len(head) > 104 and (head[104] & 0xC0) == 0x80
        return ".laz" if compressed else ".las"
    if head.startswith(b"glTF"):
        return ".glb"
    if (total_size is not None and total_size >= 84
            and 84 + 50 * int.from_bytes(head[80:84], "little") == total_size):
        return ".stl"
    lines = _text_lines(head)
    if not lines:
        return None
    first = lines[0]
    if first.startswith(b"{") and b'"asset"' in head:
        return ".gltf"
    if first.split()[0] in _OFF_KEYWORDS:
        return ".off"
    if first.lower().startswith(b"solid") and b"facet" in head:
        return ".stl"
    words = [ln.split() for ln in lines[:200]]
    if any(w[0] in (b"v", b"vn", b"vt", b"f", b"o", b"g", b"mtllib", b"usemtl") for w in words) \
            and sum(w[0] == b"v" for w in words) >= 1:
        return ".obj"
    numeric = [w for w in words if all(_NUMBER.match(x) for x in w)]
    if numeric and len(numeric) >= len(words) - 1 and any(len(w) >= 3 for w in numeric):
        ext = Path(name_hint.lower().removesuffix(".gz")).suffix
        return ext if ext in TEXT_CLOUDS else ".xyz"
    return None


def _describe(head: bytes) -> str:
    shown = head[:16]
    printable = all(32 <= b < 127 or b in (9, 10, 13) for b in shown)
    return repr(shown.decode("ascii")) if printable else shown.hex(" ")


def _not_a_scan(name: str, head: bytes) -> UploadError:
    kinds = ("PLY, OBJ, STL, OFF, glTF/GLB, XYZ/PTS/ASC, each optionally .gz, E57, LAS/LAZ, "
             "or a .zip of one")
    return UploadError(f"{name or 'the upload'}: the content is not a scan format Tessera "
                       f"reads ({kinds}); it starts with {_describe(head)}")


def _refuse_gzipped(fmt: str, name: str) -> None:
    """Refuse a gzip stream of a format whose reader needs the file itself (E57, LAS/LAZ:
    ``fitter.fitting.io.NOT_GZIPPED``)."""
    if fmt in NOT_GZIPPED:
        raise UploadError(f"{name}: a gzip-compressed {fmt} is not read (its reader needs the "
                          "file itself, with random access); upload it uncompressed"
                          + (" or as LAZ" if fmt == ".las" else ""))


# --------------------------------------------------------------------------- gzip
def check_gzip(path: Path, limits: UploadLimits, budget: InputBudget | None = None,
               name: str | None = None) -> bytes:
    """Decompress ``path`` to nowhere within the limits; return the first decompressed bytes.

    ``budget`` (default: a fresh one of ``limits``) is shared by the several ``.gz`` files
    of one ``.conf``, so that their decompressed bytes count together; ``name`` is the
    file's name in the messages (default: its stored name).

    Raises
    ------
    UploadError
        Corrupt gzip, or output over ``limits.max_expanded_bytes`` or over
        ``limits.max_ratio`` times the compressed size.
    """
    budget = budget if budget is not None else InputBudget(limits)
    head = bytearray()
    buffer = bytearray(CHUNK)
    try:
        with open(path, "rb") as raw:
            source = HashingReader(raw, GZIP_READ_BYTES)
            bounded = BoundedReader(gzip.GzipFile(fileobj=source, mode="rb"), source,
                                    name or path.name, path.stat().st_size, budget,
                                    declared_gzip_size(path))
            while n := bounded.readinto(buffer):
                if len(head) < SNIFF_BYTES:
                    head += buffer[:min(n, SNIFF_BYTES - len(head))]
            total = bounded.nbytes
    except ScanError as exc:
        raise UploadError(f"refused as a decompression bomb: {exc}") from None
    except (gzip.BadGzipFile, EOFError, zlib.error) as exc:
        raise UploadError(f"the gzip stream is corrupt or truncated: {exc}") from None
    if total == 0:
        raise UploadError("the gzip stream decompresses to 0 bytes (an empty file)")
    return bytes(head)


def check_conf(conf: Path, root: Path, limits: UploadLimits) -> None:
    """Check an uploaded ``.conf`` as the fit will read it: every line parsed, every named
    file inside the ``.conf``'s folder (within ``root``, the extracted upload), named
    once, at most ``limits.max_files`` of them, and every ``.gz`` among them decompressed
    to the counter with one shared ``max_expanded_bytes``.

    Raises
    ------
    UploadError
        Naming the ``.conf`` (relative to ``root``), the line's file and what is wrong.
    """
    budget = InputBudget(limits)
    shown = conf.relative_to(root).as_posix()
    try:
        entries, _, _ = read_conf(conf, conf.suffix.lower() == ".gz", budget)
        listed = check_registration(conf, entries, budget)
    except ScanError as exc:  # its message starts with the .conf's name: show its path
        raise UploadError(f"{shown}{str(exc).removeprefix(conf.name)}") from None
    for file in listed:
        if file.suffix.lower() == ".gz":
            check_gzip(file, limits, budget)


# ---------------------------------------------------------------------------- zip
def safe_member_path(name: str) -> PurePosixPath:
    """A zip member's name as a relative path that stays inside the extraction folder.

    Raises
    ------
    UploadError
        Absolute names (``/x``, ``\\\\x``, ``C:x``), ``..`` components, empty names.
    """
    unified = name.replace("\\", "/")
    if unified.startswith("/") or re.match(r"^[A-Za-z]:", unified):
        raise UploadError(f"zip member {name!r} has an absolute path; refused (members must "
                          "stay inside the archive's folder)")
    parts = [p for p in unified.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise UploadError(f"zip member {name!r} leads out of its folder with '..'; refused")
    if not parts:
        raise UploadError(f"zip member {name!r} has an empty name")
    return PurePosixPath(*parts)


def _scan_members(names: list[PurePosixPath]) -> list[PurePosixPath]:
    def ext(p: PurePosixPath) -> str:
        suffixes = [s.lower() for s in p.suffixes]
        if suffixes and suffixes[-1] == ".gz":
            suffixes = suffixes[:-1]
        return suffixes[-1] if suffixes else ""

    confs = [p for p in names if ext(p) == ".conf"]
    if confs:
        return confs
    return [p for p in names if ext(p) in SUPPORTED_EXTENSIONS and not p.name.startswith(".")]


def extract_zip(path: Path, target: Path, limits: UploadLimits) -> Path:
    """Check and extract the zip ``path`` into ``target``; return the scan file inside.

    Raises
    ------
    UploadError
        A member name outside the folder, a link, too many members, sizes or
        ratios over the limits (declared or real), a corrupt archive, or not
        exactly one scan.
    """
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise UploadError(f"the zip archive is corrupt: {exc}") from None
    with archive:
        infos = [i for i in archive.infolist() if not i.is_dir()]
        if len(infos) > limits.max_members:
            raise UploadError(f"the zip has {len(infos)} members; at most "
                              f"{limits.max_members} are accepted")
        declared = 0
        members: list[tuple[zipfile.ZipInfo, PurePosixPath]] = []
        for info in archive.infolist():
            rel = safe_member_path(info.filename)
            if stat.S_ISLNK(info.external_attr >> 16):
                raise UploadError(f"zip member {info.filename!r} is a symbolic link; refused")
            if info.is_dir():
                continue
            if info.file_size > limits.max_ratio * max(info.compress_size, 1):
                raise UploadError(
                    f"zip member {info.filename!r} declares {format_size(info.file_size)} from "
                    f"{format_size(info.compress_size)} (ratio over {limits.max_ratio:g}): refused "
                    "as a decompression bomb")
            declared += info.file_size
            members.append((info, rel))
        if declared > limits.max_expanded_bytes:
            raise UploadError(f"the zip's members total {format_size(declared)}, over the limit of "
                              f"{format_size(limits.max_expanded_bytes)}: refused as a "
                              "decompression bomb")
        seen = {str(rel).lower() for _, rel in members}
        if len(seen) != len(members):
            raise UploadError("the zip has two members with the same name")
        scans = _scan_members([rel for _, rel in members])
        if len(scans) != 1:
            listed = ", ".join(str(s) for s in scans[:5]) or "none"
            raise UploadError(f"the zip must hold exactly one scan file (or one .conf with its "
                              f"range scans); found {len(scans)}: {listed}")
        target.mkdir(parents=True, exist_ok=True)
        total = 0
        try:
            for info, rel in members:
                dest = target.joinpath(*rel.parts)
                if target.resolve() not in dest.resolve().parents:
                    raise UploadError(f"zip member {info.filename!r} leads out of its folder")
                dest.parent.mkdir(parents=True, exist_ok=True)
                written = 0
                with archive.open(info) as src, open(dest, "xb") as out:
                    while chunk := src.read(CHUNK):
                        written += len(chunk)
                        total += len(chunk)
                        if written > info.file_size or total > limits.max_expanded_bytes:
                            raise UploadError(f"zip member {info.filename!r} expands beyond its "
                                              "declared size: refused as a decompression bomb")
                        out.write(chunk)
        except (zipfile.BadZipFile, zlib.error, EOFError) as exc:
            raise UploadError(f"the zip archive is corrupt: {exc}") from None
        except NotImplementedError as exc:  # an unsupported compression method
            raise UploadError(f"the zip archive cannot be read: {exc}") from None
    return target.joinpath(*scans[0].parts)


# ------------------------------------------------------------------------ preparing
def prepare_scan(received: ReceivedFile, limits: UploadLimits) -> PreparedScan:
    """Identify the received bytes and give them their stored name (see the module doc).

    Raises
    ------
    UploadError
        Not a scan format, a bad or oversized archive.
    """
    directory = received.path.parent
    with open(received.path, "rb") as fh:
        head = fh.read(SNIFF_BYTES)
    name = received.original_name
    if head.startswith(b"\x1f\x8b"):
        inner = check_gzip(received.path, limits, name=name or "the upload")
        fmt = sniff_format(inner, None, name)
        if fmt is None:
            raise _not_a_scan(name, inner)
        _refuse_gzipped(fmt, name or "the upload")
        stored = directory / f"scan{fmt}.gz"
        os.replace(received.path, stored)
        return PreparedScan(stored, fmt.lstrip("."), "gzip")
    if head.startswith(b"PK\x03\x04") or head.startswith(b"PK\x05\x06"):
        archive = directory / "upload.zip"
        os.replace(received.path, archive)
        extracted = directory / "files"
        try:
            scan = extract_zip(archive, extracted, limits)
        except UploadError:
            shutil.rmtree(extracted, ignore_errors=True)
            raise
        with open(scan, "rb") as fh:
            inner_head = fh.read(SNIFF_BYTES)
        suffix = scan.suffix.lower()
        if suffix == ".gz":
            inner_head = check_gzip(scan, limits)
            suffix = Path(scan.stem).suffix.lower()
            _refuse_gzipped(suffix, f"{name}:{scan.relative_to(extracted)}")
        if suffix == ".conf":
            check_conf(scan, extracted, limits)
        else:
            size = scan.stat().st_size if scan.suffix.lower() != ".gz" else None
            fmt = sniff_format(inner_head, size, scan.name)
            if fmt is None:
                raise _not_a_scan(f"{name}:{scan.relative_to(extracted)}", inner_head)
            if fmt != suffix and not (fmt in TEXT_CLOUDS and suffix in TEXT_CLOUDS):
                raise UploadError(f"{name}:{scan.relative_to(extracted)}: the name says "
                                  f"{suffix} but the content is {fmt}")
        return PreparedScan(scan, suffix.lstrip("."), "zip")
    fmt = sniff_format(head, received.bytes, name)
    if fmt is None:
        raise _not_a_scan(name, head)
    stored = directory / f"scan{fmt}"
    os.replace(received.path, stored)
    return PreparedScan(stored, fmt.lstrip("."), None)
