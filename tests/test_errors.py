"""One exception base: every error Tessera raises on purpose is a ``TesseraError``, the
table in ``client_py.errors`` lists them all, and a state conflict is not a ``ValueError``
(a broad ``except ValueError`` must not turn it, or a bug, into the wrong answer)."""

from __future__ import annotations

import importlib
import pkgutil
import re

import pytest

import client_py
import fitter
from client_py.errors import PatchFormatError, TesseraError
from fitter.collection.catalog import ConflictError


def _error_classes() -> dict[str, type]:
    """Every exception class defined in a module of client_py or fitter, by dotted name."""
    found = {}
    for package in (client_py, fitter):
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            module = importlib.import_module(info.name)
            for name, value in vars(module).items():
                if (isinstance(value, type) and issubclass(value, BaseException)
                        and value.__module__ == info.name):
                    found[f"{info.name}.{name}"] = value
    return found


def test_every_error_class_derives_from_the_one_base():
    classes = _error_classes()
    assert len(classes) >= 9
    outside = sorted(name for name, cls in classes.items() if not issubclass(cls, TesseraError))
    assert outside == []


def test_the_base_lists_every_specific_error():
    listed = {n for n in re.findall(r"``([\w.]+Error)``", client_py.errors.__doc__) if "." in n}
    defined = {name for name in _error_classes() if not name.endswith(".TesseraError")
               and not name.rsplit(".", 1)[1].startswith("_")}  # private: never escapes
    # the table names each class where callers import it from (a package may re-export)
    short = {name.rsplit(".", 1)[1] for name in defined}
    assert short == {name.rsplit(".", 1)[1] for name in listed}


def test_a_conflict_is_not_a_bad_value():
    assert not issubclass(ConflictError, ValueError)
    with pytest.raises(TesseraError):
        raise PatchFormatError(0, "x")
