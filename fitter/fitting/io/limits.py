"""The input limits of a scan read: one definition for the command line and the uploads.

A scan file may be hostile or merely careless: a small ``.gz`` that expands to gigabytes,
a ``.conf`` that lists ``/etc/passwd``, ``../../elsewhere`` or the same 3,000-point file
two thousand times, a text cloud of 10^9 rows. :class:`InputLimits` (frozen) says what a
read accepts; :class:`InputBudget` (one per ``load_scan`` call, shared by every file a
``.conf`` names) counts what the read has used so far and refuses, with a
``ScanError`` naming the file, the limit and the setting that raises it, as soon as a
count passes its limit:

======================  ==========  =============================================
limit                   default     counted
======================  ==========  =============================================
``max_expanded_bytes``  4 GiB       decompressed bytes of every gzip stream of the
                                    read (all the files of a ``.conf`` together)
``max_ratio``           200         decompressed / compressed bytes of one stream
``max_points``          2 x 10^7    points of the read (all files), counted before
                                    they are allocated (text: as they are parsed)
``max_files``           1000        scan files one ``.conf`` names
======================  ==========  =============================================

Each is raised on the command line by ``tessera fit --max-expanded-bytes``,
``--max-ratio``, ``--max-points``, ``--max-files``, and for the admin uploads by the
settings ``TESSERA_UPLOAD_MAX_EXPANDED_BYTES``, ``..._MAX_RATIO``, ``..._MAX_POINTS``,
``..._MAX_FILES`` (:data:`RAISED_BY`; the refusal names the one that applies).

Every file a ``.conf`` names must lie inside the ``.conf``'s own folder
(:func:`confined_path`: no absolute name, no ``..`` leading out, no symbolic link
pointing out) and may be named once.

Why these defaults: binary PLY compresses 2-4x and ASCII clouds 5-10x, so a ratio of
200 refuses only bombs; a fit holds about 500 bytes per point at its peak (measured on a
6-million-point registration: 3 GB), so 2 x 10^7 points is about 10 GB — thin larger
scans (``thin=``) or raise the limit. A gzip stream's size is also checked before it is
read, from the uncompressed size its trailer states (ISIZE, RFC 1952; modulo 2^32, so
it can only under-state a large file, which the streamed count then catches), and the
ratio is held while the stream is read too: the bytes decompressed so far may not pass
``max_ratio`` times the compressed bytes read so far (plus 256 KiB), so a bomb whose
trailer lies is refused after a few megabytes, not after ``max_ratio`` times its size.

Only the standard library here: the server's upload checks use these limits too.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields
from pathlib import Path, PurePath

from .scan import ScanError

#: each limit's command-line flag and server setting, for the refusal messages
RAISED_BY = {
    "max_expanded_bytes": ("--max-expanded-bytes", "TESSERA_UPLOAD_MAX_EXPANDED_BYTES"),
    "max_ratio": ("--max-ratio", "TESSERA_UPLOAD_MAX_RATIO"),
    "max_points": ("--max-points", "TESSERA_UPLOAD_MAX_POINTS"),
    "max_files": ("--max-files", "TESSERA_UPLOAD_MAX_FILES"),
}
CONTEXTS = ("cli", "upload")
#: decompressed bytes a stream may run ahead of ``max_ratio`` times its bytes read so far
RATIO_SLACK_BYTES = 256 << 10


def format_bytes(nbytes: float) -> str:
    """``nbytes`` for a message: ``"512 bytes"``, ``"3.5 MiB"``."""
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if nbytes < 1024 or unit == "GiB":
            return f"{nbytes:.0f} {unit}" if unit == "bytes" else f"{nbytes:.1f} {unit}"
        nbytes /= 1024
    return f"{nbytes} bytes"  # pragma: no cover - the loop always returns


@dataclass(frozen=True)
class InputLimits:
    """What one scan read accepts (see the module docstring's table).

    Attributes
    ----------
    max_expanded_bytes : int
        Decompressed bytes of all the gzip streams of one read, ``>= 1``.
    max_ratio : float
        Decompressed / compressed size of one gzip stream, ``>= 1``.
    max_points : int
        Points of one read (a ``.conf``: of all its scans together), ``>= 1``.
    max_files : int
        Scan files one ``.conf`` may name, ``>= 1``.
    context : str
        ``"cli"`` or ``"upload"``: which spelling of each limit the refusals name
        (``--max-points`` or ``TESSERA_UPLOAD_MAX_POINTS``).

    Raises
    ------
    ValueError
        A limit that is not a number ``>= 1`` or an unknown ``context``.
    """

    max_expanded_bytes: int = 4 << 30
    max_ratio: float = 200.0
    max_points: int = 20_000_000
    max_files: int = 1000
    context: str = "cli"

    def __post_init__(self) -> None:
        for f in fields(InputLimits):
            if f.name == "context":
                continue
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 1:
                raise ValueError(f"{f.name} must be a number >= 1, got {value!r}")
        if self.context not in CONTEXTS:
            raise ValueError(f"context must be one of {', '.join(CONTEXTS)}, got "
                             f"{self.context!r}")

    def raised_by(self, limit: str) -> str:
        """How the user raises ``limit``: its flag (``cli``) or its setting (``upload``)."""
        return RAISED_BY[limit][CONTEXTS.index(self.context)]

    def refusal(self, name: str, what: str, limit: str, shown: str) -> ScanError:
        """``ScanError("NAME: WHAT, over the limit LIMIT = SHOWN (raise it with ...)")``."""
        return ScanError(f"{name}: {what}, over the limit {limit} = {shown}; refused (raise it "
                         f"with {self.raised_by(limit)} if the input is genuine)")


class InputBudget:
    """What one ``load_scan`` call has used of its :class:`InputLimits` so far.

    Readers call :meth:`take_points` before they allocate the points of a file (or as
    they parse, chunk by chunk), the gzip reader calls :meth:`take_expanded` for every
    chunk it decompresses, and a ``.conf`` calls :meth:`take_file` for every scan it
    names; each refuses with a ``ScanError`` once the read passes a limit.
    """

    def __init__(self, limits: InputLimits | None = None) -> None:
        self.limits = limits or InputLimits()
        self.points = 0
        self.expanded_bytes = 0
        self.files: set[Path] = set()

    def take_points(self, name: str, count: int) -> None:
        """Count ``count`` more points of the file ``name``; refuse past ``max_points``."""
        self.points += int(count)
        if self.points > self.limits.max_points:
            what = (f"{count:,} points" if self.points == count
                    else f"{count:,} more points make {self.points:,} in all")
            raise self.limits.refusal(name, what, "max_points", f"{self.limits.max_points:,}")

    def check_declared_size(self, name: str, compressed: int, declared: int) -> None:
        """Refuse a gzip stream whose trailer declares more than it may expand to."""
        self._check_expanded(name, compressed, compressed, declared, declared, "declares")

    def take_expanded(self, name: str, compressed: int, consumed: int, stream_total: int,
                      count: int) -> None:
        """Count ``count`` more decompressed bytes of the gzip file ``name``: ``compressed``
        bytes stored, ``consumed`` of them read so far, ``stream_total`` decompressed with
        these. Refuses past ``max_expanded_bytes`` (all streams of the read) or past
        ``max_ratio`` — of the whole file, and of the part read so far (plus
        ``RATIO_SLACK_BYTES``), so that a bomb is refused early, not after ``max_ratio``
        times its size.
        """
        self._check_expanded(name, compressed, consumed, stream_total, count,
                             "expands to more than")
        self.expanded_bytes += count

    def _check_expanded(self, name: str, compressed: int, consumed: int, stream_total: int,
                        count: int, verb: str) -> None:
        if self.expanded_bytes + count > self.limits.max_expanded_bytes:
            raise self.limits.refusal(
                name, f"the gzip stream {verb} {format_bytes(self.expanded_bytes + count)} "
                "(all decompressed input of this read)", "max_expanded_bytes",
                format_bytes(self.limits.max_expanded_bytes))
        ratio = self.limits.max_ratio
        whole = stream_total > ratio * max(compressed, 1)
        if whole or stream_total > ratio * consumed + RATIO_SLACK_BYTES:
            shown = compressed if whole else consumed
            part = "" if whole else " read so far"
            raise self.limits.refusal(
                name, f"the gzip stream {verb} {format_bytes(stream_total)} from the "
                f"{format_bytes(shown)}{part} (ratio {stream_total / max(shown, 1):.0f}): "
                "a decompression bomb", "max_ratio", f"{ratio:g}")

    def take_file(self, listed_by: str, path: Path) -> None:
        """Count one more scan file a ``.conf`` names (``path`` resolved); refuse a second
        naming of the same file and more than ``max_files`` files."""
        if path in self.files:
            raise ScanError(f"{listed_by}: names {path.name} more than once; each scan file "
                            "may be registered once")
        self.files.add(path)
        if len(self.files) > self.limits.max_files:
            raise self.limits.refusal(listed_by, f"names more than {self.limits.max_files:,} "
                                      "scan files", "max_files", f"{self.limits.max_files:,}")


def confined_path(root: Path, name: str, listed_by: str) -> Path:
    """The file ``name`` (as a ``.conf`` line spells it) inside the folder ``root``.

    Returns ``root / name`` (not resolved, so the caller's ``.gz`` fallback still
    works); refuses names that could lead outside ``root``.

    Raises
    ------
    ScanError
        An absolute name (``/x``, ``\\\\x``, ``C:x``), a ``..`` component, or a path
        whose resolved location (symbolic links followed) is outside ``root``.
    """
    unified = name.replace("\\", "/")
    if unified.startswith("/") or (len(unified) > 1 and unified[1] == ":"):
        raise ScanError(f"{listed_by}: names {name!r}, an absolute path; a registration's "
                        "scans must be named relative to its own folder")
    parts = PurePath(unified).parts
    if ".." in parts:
        raise ScanError(f"{listed_by}: names {name!r}, which leads out of its folder with "
                        "'..'; a registration's scans must lie in its own folder")
    path = root.joinpath(*parts)
    top = Path(os.path.realpath(root))
    for candidate in (path, path.with_name(path.name + ".gz")):
        if os.path.lexists(candidate):
            real = Path(os.path.realpath(candidate))
            if real != top and top not in real.parents:
                raise ScanError(f"{listed_by}: names {name!r}, a link to {real} outside its "
                                f"folder {top}; refused")
    return path
