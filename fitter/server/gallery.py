"""The ``gallery`` blueprint: the collection's front page, one card per object."""

from __future__ import annotations

from flask import Blueprint, current_app, render_template
from flask.typing import ResponseReturnValue

from .api import object_summary

bp = Blueprint("gallery", __name__)


@bp.app_template_filter("byte_size")
def byte_size(n: int | None) -> str:
    """``n`` bytes as the pages write them: ``B`` below 1 KiB, ``KB`` below 1 MiB, else ``MB``
    (binary multiples, one decimal; ``formatBytes`` of web/src/page.js); ``—`` for None."""
    if n is None:
        return "—"
    if n < 1024:
        return f"{n} B"
    return f"{n / 1024:.1f} KB" if n < 1024 * 1024 else f"{n / 1024 / 1024:.1f} MB"


@bp.get("/")
def index() -> ResponseReturnValue:
    """Cards with title, thumbnail, bundle size and fit error of every object."""
    collection = current_app.extensions["tessera_collection"]
    cards = [object_summary(bundle) for bundle in collection.bundles()]
    return render_template("gallery.html", cards=cards)
