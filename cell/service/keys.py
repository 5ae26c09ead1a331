"""API keys of the service: roles and what each may do, key generation and hashing, and the in-memory
key ring the request path authenticates against.

A key is ``cell_`` followed by 43 URL-safe characters (256 random bits). Only its hex SHA-256 is stored:
a fast hash is enough for a random key of that length (nothing to guess), and it lets a request find its
key by one dictionary lookup. A key is shown once, when ``cell keys create`` makes it, and never logged.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
from enum import StrEnum

from cell.service.store import KeyRecord, Store
from drivers.errors import ServiceError

KEY_PREFIX = "cell_"
KEY_RANDOM_BYTES = 32  # 256 bits of randomness per key
KEY_NAME = re.compile(r"[A-Za-z0-9._-]{1,64}")  # what a key's name may be
SECRET_SHAPE = re.compile(rf"{KEY_PREFIX}[A-Za-z0-9_-]{{43}}")  # what a key looks like: no name may


class Role(StrEnum):
    """Who holds a key: ``viewer`` watches (a screen on the shop floor), ``operator`` runs scans,
    ``line`` is a packaging line's controller, ``admin`` manages keys and data."""

    VIEWER = "viewer"
    OPERATOR = "operator"
    LINE = "line"
    ADMIN = "admin"


class Permission(StrEnum):
    """What a request may do: read jobs and status, stop the arm, submit, cancel a queued job, recover
    after a stop, upload an object mesh, drive the line interface, switch the line's unit mode (Production
    or the operator's Manual), manage keys, purge old jobs, mark a job kept from retention."""

    READ = "read"
    STOP = "stop"
    SUBMIT = "submit"
    CANCEL = "cancel"
    RECOVER = "recover"
    UPLOAD = "upload"
    LINE = "line"
    MODE = "mode"
    KEYS = "keys"
    PURGE = "purge"
    KEEP = "keep"


# Each role's permissions. STOP is every role's: stopping the arm is never refused to a known key.
PERMISSIONS: dict[Role, frozenset[Permission]] = {
    Role.VIEWER: frozenset({Permission.READ, Permission.STOP}),
    Role.OPERATOR: frozenset({Permission.READ, Permission.STOP, Permission.SUBMIT, Permission.CANCEL,
                              Permission.RECOVER, Permission.UPLOAD, Permission.MODE, Permission.KEEP}),
    Role.LINE: frozenset({Permission.READ, Permission.STOP, Permission.LINE, Permission.MODE}),
    Role.ADMIN: frozenset(Permission),
}


def new_key() -> str:
    """A fresh random key: ``cell_`` and 256 random bits, URL-safe base64."""
    return KEY_PREFIX + secrets.token_urlsafe(KEY_RANDOM_BYTES)


def hash_key(key: str) -> str:
    """The hex SHA-256 of ``key``, as stored and looked up."""
    return hashlib.sha256(key.encode()).hexdigest()


def parse_role(role: str) -> Role:
    """``role`` as a :class:`Role`; ``ServiceError`` (``invalid``, field ``role``) naming the roles
    otherwise."""
    try:
        return Role(role)
    except ValueError:
        raise ServiceError(f"unknown role {role!r} (roles: {', '.join(Role)})", reason="invalid",
                           field="role") from None


def create_key(store: Store, role: str, name: str | None) -> tuple[KeyRecord, str]:
    """Make a key of ``role`` named ``name`` (1-64 characters of letters, digits, ``.``, ``_``, ``-``;
    default ``<role>-<6 hex>``), store its hash, and return its record and the key itself, which is not
    kept anywhere. ``ServiceError``: ``invalid`` for a bad role or name, ``conflict`` for a name taken."""
    checked = parse_role(role)
    if name is None:
        name = f"{checked.value}-{secrets.token_hex(3)}"
    elif not KEY_NAME.fullmatch(name):
        raise ServiceError(f"key name {name!r}: expected 1 to 64 letters, digits, '.', '_' or '-'",
                           reason="invalid", field="name")
    elif SECRET_SHAPE.fullmatch(name):  # a name is logged and shown, a secret never
        raise ServiceError(f"key name {name[:8]}...: a key's name may not look like a key (cell_ and 43 "
                           "characters)", reason="invalid", field="name")
    key = new_key()
    return store.add_key(name, checked.value, hash_key(key)), key


def allowed(role: str, permission: Permission) -> bool:
    """Whether a key of ``role`` may do ``permission`` (an unknown role may do nothing)."""
    try:
        return permission in PERMISSIONS[Role(role)]
    except ValueError:
        return False


class KeyRing:
    """In-memory view of the active keys for the service's request path: authenticate() never touches
    the database; refresh() (called by the service every second in the background) reloads it."""

    def __init__(self, store: Store) -> None:
        """Load the active keys of ``store`` once (``StoreError`` if it cannot be read)."""
        self._store = store
        self._by_hash: dict[str, KeyRecord] = {}
        self.refresh()

    def refresh(self) -> None:
        """Reload the active keys: a key created or revoked since counts from now. On a ``StoreError``
        the previous view stays in use and the error is raised. The view is swapped in one assignment:
        a request on another thread sees the old one or the new one, never a mix."""
        self._by_hash = {record.key_hash: record for record in self._store.active_keys()}

    def authenticate(self, key: str) -> KeyRecord | None:
        """The active key's record, or None for an unknown or revoked key."""
        digest = hash_key(key)
        record = self._by_hash.get(digest)
        if record is None or not hmac.compare_digest(record.key_hash, digest):
            return None
        return record

    def active(self, record: KeyRecord) -> bool:
        """Whether ``record``'s key still authenticates (a long request, an event stream, asks again
        while it runs: the key may have been revoked since it began)."""
        return record.key_hash in self._by_hash

    def __len__(self) -> int:
        """The number of active keys."""
        return len(self._by_hash)
