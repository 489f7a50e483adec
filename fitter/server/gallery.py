"""The ``gallery`` blueprint: the collection's front page, one card per object."""

from __future__ import annotations

from flask import Blueprint, current_app, render_template
from flask.typing import ResponseReturnValue

from .api import object_summary

bp = Blueprint("gallery", __name__)


@bp.get("/")
def index() -> ResponseReturnValue:
    """Cards with title, thumbnail, bundle size and fit error of every object."""
    collection = current_app.extensions["tessera_collection"]
    cards = [object_summary(bundle) for bundle in collection.bundles()]
    return render_template("gallery.html", cards=cards)
