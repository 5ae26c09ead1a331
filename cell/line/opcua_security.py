"""Who may talk to the cell's OPC UA server, and the server's own certificate.

- The server's certificate and private key (for ``sign-and-encrypt``, Basic256Sha256) are made on first
  start in ``<data_dir>/opcua/`` and reused after, so that a PLC trusts the server once: the key is PEM
  (PKCS#8, file mode 0600, its folder 0700), the certificate DER, self-signed. A certificate is made anew
  only when it is missing or has expired; the PLC must then trust the new one.
- A client logs in with the user name and password of an API key (``cell keys create --role line``): the
  key's name and its secret. The key must be active and its role must have ``Permission.LINE`` (a
  ``line`` key, or an ``admin`` key). There is no anonymous login.
- Every request of a session after its login is checked again (:class:`LinePermissions`): a key revoked
  since the login is refused from its next request on, as the REST API refuses it on its next request.
  The secret is kept in the session's user object for that check; it is never logged or shown.
"""

from __future__ import annotations

import contextvars
import datetime
import ipaddress
import logging
import os
import socket
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from asyncua import ua
from asyncua.crypto import cert_gen
from asyncua.crypto.permission_rules import USER_TYPES, SimpleRoleRuleset, User, UserRole
from asyncua.server.user_managers import UserManager
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID

from cell.service.keys import SECRET_SHAPE, KeyRing, Permission, allowed
from cell.service.store import KeyRecord
from drivers.errors import ConfigError

if TYPE_CHECKING:
    from asyncua.server.internal_server import InternalServer

log = logging.getLogger("cell.line")

CERT_DAYS = 3650
"""How long a generated server certificate is valid [days]: ten years, so that the line's PLCs, which trust
it by hand, do not have to trust a new one every year."""
CERT_FILE = "server-cert.der"
KEY_FILE = "server-key.pem"

caller: contextvars.ContextVar[str | None] = contextvars.ContextVar("opcua_caller", default=None)
"""The key name of the session whose request is being processed (set by :class:`LinePermissions` before
each request): a method's handler reads it, as asyncua hands a method no session."""


@dataclass
class LineUser(User):
    """A logged-in OPC UA session: ``name`` is the key's name; ``secret`` the key itself, kept to check at
    each request that the key is still active (not in ``repr``: asyncua logs the user)."""

    secret: str = field(default="", repr=False, compare=False)


def _login(keys: KeyRing, username: str, secret: str) -> KeyRecord | str:
    """The active key of ``keys`` that logs in as ``username`` with the password ``secret`` and may drive
    the line; else why the login is refused, in words for the cell's log. The PLC is told only
    ``BadUserAccessDenied``, so the integrator commissioning it reads the cause here, which tells the usual
    mistakes apart: a key of another role, a user name that is not the key's, a secret that is no active
    key's (mistyped, revoked, or made in another store). Nothing of the secret is said, and no other key
    is named. Asked again at every request of a logged-in session (:class:`LinePermissions`): the key may
    have been revoked since."""
    if not username or not secret:
        return "no user name or no password: the user name is a key's name, the password its secret"
    if SECRET_SHAPE.search(username):  # also with a space or a line end pasted with it
        return ("the user name is a key's secret: the user name is the key's name, the password its secret "
                "(swapped?)")
    record = keys.authenticate(secret)
    if record is None or not record.active:
        return ("the password is no active key's secret: a mistyped secret, or a key revoked or made in "
                "another store than this service's (cell keys list --data-dir, as the service's user)")
    if record.name != username:
        return ("the password is another key's secret: the user name must be the name of the key whose "
                "secret it is")
    if not allowed(record.role, Permission.LINE):
        return (f"key {record.name} has role {record.role}, which may not drive the line: give the PLC a "
                "key of role line (cell keys create --role line)")
    return record


class LineUserManager(UserManager):
    """asyncua's user manager: user name = a key's name, password = its secret (see the module
    docstring). Called by asyncua on the event loop at each session activation; the key ring is
    in memory, so it does not block."""

    def __init__(self, keys: KeyRing) -> None:
        self._keys = keys

    def get_user(self, iserver: InternalServer, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        """The session's user, or None (asyncua answers ``BadUserAccessDenied``, and the cell's log says
        why: :func:`_login`)."""
        secret = password or ""
        login = _login(self._keys, username or "", secret)
        if isinstance(login, str):
            shown = "<a key's secret, not shown>" if SECRET_SHAPE.search(username or "") \
                else repr((username or "")[:64])
            log.warning("OPC UA: login refused for user name %s: %s", shown, login)
            return None
        log.info("OPC UA: key %s logged in", login.name)
        return LineUser(role=UserRole.User, name=login.name, secret=secret)


class LinePermissions(SimpleRoleRuleset):
    """Checked by asyncua before every request of a session: a logged-in line key (still active) may
    read, browse, subscribe, write and call; nothing else may do anything (an unactivated session's
    user is anonymous). Node management (adding or deleting nodes) is nobody's."""

    def __init__(self, keys: KeyRing) -> None:
        super().__init__()
        self._keys = keys
        self._allowed = frozenset(ua.NodeId(ua.Int32(type_id)) for type_id in USER_TYPES)

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: Any) -> bool:
        if not isinstance(user, LineUser) or action_type_id not in self._allowed:
            return False
        if isinstance(_login(self._keys, user.name or "", user.secret), str):
            log.warning("OPC UA: key %s was revoked: its session is refused", user.name)
            return False
        caller.set(user.name)
        return True


# ---------------------------------------------------------------------------------------- certificate


def _host_names(hosts: list[str]) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return names


def _write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` readable by its owner only (0600, also when the file existed)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as out:
        os.fchmod(out.fileno(), 0o600)
        out.write(data)


def ensure_certificate(folder: Path, app_uri: str, endpoint_host: str) -> tuple[Path, Path]:
    """The server's certificate and private key files in ``folder`` (see the module docstring), made
    when missing; the certificate names ``app_uri`` (OPC UA requires it in the subject alternative name),
    this machine's host name and ``endpoint_host``. ``ConfigError`` when the folder cannot be written or
    a file there cannot be read."""
    cert_path, key_path = folder / CERT_FILE, folder / KEY_FILE
    try:
        folder.mkdir(parents=True, exist_ok=True)
        folder.chmod(0o700)
        if key_path.is_file():
            key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
            if not isinstance(key, rsa.RSAPrivateKey):
                raise ValueError("not an RSA key")
        else:
            key = cert_gen.generate_private_key()
            _write_private(key_path, cert_gen.dump_private_key_as_pem(key))
            cert_path.unlink(missing_ok=True)  # a certificate of another key is of no use
        if cert_path.is_file():
            cert = x509.load_der_x509_certificate(cert_path.read_bytes())
            if cert.not_valid_after_utc > datetime.datetime.now(datetime.UTC):
                return cert_path, key_path
            log.warning("OPC UA: the server certificate %s expired on %s: a new one is made; the PLCs must "
                        "trust it", cert_path, cert.not_valid_after_utc.date())
        hosts = list(dict.fromkeys([socket.gethostname(), endpoint_host]))
        cert = cert_gen.generate_self_signed_app_certificate(
            key, app_uri, {"organizationName": "cell"},
            [x509.UniformResourceIdentifier(app_uri), *_host_names(hosts)],
            [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH], days=CERT_DAYS)
        cert_path.write_bytes(cert.public_bytes(serialization.Encoding.DER))
        log.warning("OPC UA: made the server certificate %s (SHA-256 %s): the line's PLCs must trust it",
                    cert_path, fingerprint(cert_path))
    except (OSError, ValueError) as exc:
        raise ConfigError(f"the OPC UA server's certificate or key in {folder} cannot be made or read: {exc}",
                          field="line.opcua") from None
    return cert_path, key_path


def fingerprint(cert_path: Path) -> str:
    """The SHA-256 fingerprint of a DER certificate file, as ``AA:BB:...`` (what a PLC's trust dialog
    shows)."""
    digest = x509.load_der_x509_certificate(cert_path.read_bytes()).fingerprint(hashes.SHA256())
    return ":".join(f"{b:02X}" for b in digest)
