"""The product's one exception base, and the error of a bad bundle file.

Every error Tessera raises on purpose derives from :class:`TesseraError`, so a
caller at a boundary (the CLI, a job, an HTTP view) can tell a reported problem
from a bug, and catch the specific class it can answer. The specific errors live
beside the code that raises them, each a subclass of :class:`TesseraError`
(and of ``ValueError`` where the problem is a bad value or a bad file):

=========================================  ===================================
``client_py.PatchFormatError``             a bad or truncated ``.tsp``/``.tsd``
``client_py.rangecoder.RangeDecodeError``  coded bytes that end early (a
                                           ``PatchFormatError`` to its callers)
``client_py.bundle.ManifestError``         a manifest client_py cannot plan from,
                                           or a file name outside the bundle (a
                                           ``PatchFormatError``)
``fitter.fitting.io.ScanError``            an unreadable or unusable scan
``fitter.fitting.options.OptionError``     a fit option out of its range
``fitter.fitting.atlas.SurfaceError``      (a ``ScanError``) a scan without a usable surface
                                           (too few points, not repairable)
``fitter.fitting.atlas.AtlasLayoutError``  a decimated layout that is no oriented
                                           2-manifold
``fitter.fitting.atlas.AtlasFitError``     an atlas fit without working points or
                                           with a singular system
``fitter.fitting.stream.WorkingMeshError`` (a ``ScanError``) a large mesh that cannot be
                                           reduced to an atlas's working mesh
``fitter.collection.bundles.BundleError``  a bundle the server cannot serve: no or a
                                           malformed manifest, an unreadable file
``fitter.collection.catalog.CatalogError`` a catalog this code cannot use
``fitter.collection.catalog.ConflictError``  an action the current state forbids
``fitter.collection.catalog.FieldError``   an object field with a bad value
``fitter.collection.uploads.UploadError``  an upload refused (with its status)
``fitter.cli.UserError``                   a command-line problem (exit 2)
=========================================  ===================================

One more never reaches a caller: ``fitter.fitting.atlas.measure.MeasuringProcessError``,
a measuring process that failed or died; the error stage then measures that level in
its own process.
"""

from __future__ import annotations


class TesseraError(Exception):
    """Base of every error Tessera raises on purpose (never of a bug)."""


class PatchFormatError(TesseraError, ValueError):
    """A byte sequence is not a valid Tessera patch or tile.

    Attributes
    ----------
    offset : int
        Byte offset of the problem: in the file, or in the decompressed payload
        when ``section`` is ``'payload'``.
    reason : str
        What is wrong there.
    """

    def __init__(self, offset: int, reason: str, section: str = "file") -> None:
        self.offset = offset
        self.reason = reason
        self.section = section
        where = f"byte {offset}" if section == "file" else f"payload byte {offset}"
        super().__init__(f"invalid Tessera patch at {where}: {reason}")

    def __reduce__(self) -> tuple:
        """Pickle by the constructor's arguments (a worker process's error reaches its pool)."""
        return type(self), (self.offset, self.reason, self.section)
