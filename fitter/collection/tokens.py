"""The admin secret of a collection: how it is hashed, how strong it must be, where it is kept.

Only a werkzeug password hash (scrypt) of the token is ever stored, in the
catalog's settings under :data:`TOKEN_SETTING`; ``tessera admin set-token``
writes it and a running server's admin area reads it from there on its next
admin request (no restart). :data:`SESSION_VERSION_SETTING` is the counter that
``POST /admin/logout`` increments to revoke every admin session cookie.

A token is :data:`MIN_TOKEN_LENGTH` to :data:`MAX_TOKEN_LENGTH` printable ASCII
characters (:data:`TOKEN_CHARACTERS`). The same rule lets the server refuse a
presented token of any other shape at once, before the costly hash check.
"""

from __future__ import annotations

import string

from werkzeug.security import generate_password_hash

#: the catalog setting that holds the hash of the admin token
TOKEN_SETTING = "admin_token_hash"
#: the catalog setting counting logouts: a session cookie made under another value is void
SESSION_VERSION_SETTING = "admin_session_version"
MIN_TOKEN_LENGTH = 16
MAX_TOKEN_LENGTH = 256
#: the characters a token may hold: printable ASCII (what a terminal, a form and an
#: ``Authorization`` header all carry unchanged); ``--generate`` uses URL-safe base64
TOKEN_CHARACTERS = frozenset(string.ascii_letters + string.digits + string.punctuation + " ")


def hash_token(token: str) -> str:
    """A werkzeug password hash of ``token`` (what is stored, never the token)."""
    return generate_password_hash(token)


def token_shape_ok(token: str) -> bool:
    """Whether ``token`` could be an admin token at all (length and characters; no hashing)."""
    return (MIN_TOKEN_LENGTH <= len(token) <= MAX_TOKEN_LENGTH
            and TOKEN_CHARACTERS.issuperset(token))


def check_token_strength(token: str) -> None:
    """Raise ``ValueError`` for a secret too short to resist guessing, too long, or holding
    characters other than printable ASCII."""
    if len(token) < MIN_TOKEN_LENGTH:
        raise ValueError(f"the admin token must be at least {MIN_TOKEN_LENGTH} characters "
                         f"long, got {len(token)}")
    if len(token) > MAX_TOKEN_LENGTH:
        raise ValueError(f"the admin token must be at most {MAX_TOKEN_LENGTH} characters "
                         f"long, got {len(token)}")
    odd = sorted(set(token) - TOKEN_CHARACTERS)
    if odd:
        raise ValueError(f"the admin token may hold printable ASCII characters only (letters, "
                         f"digits, punctuation, space), got {''.join(odd)!r}")
