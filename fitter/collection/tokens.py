"""The admin secret of a collection: how it is hashed, how strong it must be, where it is kept.

Only a werkzeug password hash (scrypt) of the token is ever stored, in the
catalog's settings under :data:`TOKEN_SETTING`; ``tessera admin set-token``
writes it and the server's admin area checks against it.
"""

from __future__ import annotations

from werkzeug.security import generate_password_hash

#: the catalog setting that holds the hash of the admin token
TOKEN_SETTING = "admin_token_hash"
MIN_TOKEN_LENGTH = 16


def hash_token(token: str) -> str:
    """A werkzeug password hash of ``token`` (what is stored, never the token)."""
    return generate_password_hash(token)


def check_token_strength(token: str) -> None:
    """Raise ``ValueError`` for a secret too short to resist guessing."""
    if len(token) < MIN_TOKEN_LENGTH:
        raise ValueError(f"the admin token must be at least {MIN_TOKEN_LENGTH} characters "
                         f"long, got {len(token)}")
