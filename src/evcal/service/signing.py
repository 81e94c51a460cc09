"""End-to-end authentication of calibration messages: Ed25519 signatures in zenoh attachments.

Transport security (TLS, access control; docs/SECURITY.md) decides who may connect and put on
which keys. Signatures add what it cannot: a client that receives a calibration — from a
router, a bridge, a recording or an open network — checks that the service holding the
private key produced exactly these bytes. Every calibration the service publishes or sends in
reply to a query carries a small attachment (the payload itself is unchanged, so readers of
older versions are unaffected)::

    {"v": 1, "instance": "<service instance>", "key_id": "<16 hex>", "sig": <64 bytes>,
     "pub": <32 bytes>}

(msgpack). ``sig`` is the Ed25519 signature of ``b"evcal-calibration-v1\\0" + instance + b"\\0"
+ key + b"\\0" + SHA-256(payload)``: it binds the bytes to the key expression they answer and
to the instance name. ``pub`` is the raw public key: it proves nothing by itself (anyone can
sign with a key of their own), but lets a client that has no copy of the key pin it on first
use (:class:`KnownServices`, ``evcal query``'s default) and refuse any other key afterwards.
Without a key (``--sign-key`` not given) the attachment carries the instance only, unsigned,
so clients can still tell instances apart.

Keys are PEM files (PKCS#8 private, SubjectPublicKeyInfo public), made by ``evcal keygen``.
``cryptography`` (the maintained binding to OpenSSL) does the cryptography.
"""

from __future__ import annotations

import base64
import datetime
import hashlib
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack

from ..errors import ErrorReason, EvcalError

DOMAIN = b"evcal-calibration-v1"


class SignatureError(EvcalError):
    """A calibration whose signature is missing, malformed or does not verify."""

    default_reason = ErrorReason.REJECTED


def _crypto() -> Any:
    try:
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric import ed25519
    except ModuleNotFoundError as exc:  # pragma: no cover - a dependency of the extra
        raise SignatureError(f"signatures need the 'cryptography' package ({exc})") from None
    return serialization, ed25519


def _message(instance: str, key: str, payload: bytes) -> bytes:
    return b"\0".join((DOMAIN, instance.encode(), key.encode(),
                       hashlib.sha256(payload).digest()))


def key_id(public_raw: bytes) -> str:
    return hashlib.sha256(public_raw).hexdigest()[:16]


def generate_keys(prefix: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write a new key pair ``PREFIX.key`` (private, mode 600) and ``PREFIX.pub``."""
    serialization, ed25519 = _crypto()
    priv = ed25519.Ed25519PrivateKey.generate()
    key_path, pub_path = Path(f"{prefix}.key"), Path(f"{prefix}.pub")
    for p in (key_path, pub_path):
        if p.exists():
            raise SignatureError(f"{p} exists; not overwriting a key")
    fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(priv.private_bytes(serialization.Encoding.PEM,
                                   serialization.PrivateFormat.PKCS8,
                                   serialization.NoEncryption()))
    pub_path.write_bytes(priv.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))
    return key_path, pub_path


@dataclass(frozen=True)
class Signer:
    """Makes the attachment of the service's calibration messages (signed with a key)."""

    instance: str
    private: Any = None  # an Ed25519PrivateKey, or None: unsigned attachments
    key_id: str = ""
    public_raw: bytes = b""

    @classmethod
    def from_file(cls, instance: str, path: str | os.PathLike[str] | None) -> Signer:
        if path is None:
            return cls(instance)
        serialization, ed25519 = _crypto()
        try:
            priv = serialization.load_pem_private_key(Path(path).read_bytes(), password=None)
        except (OSError, ValueError, TypeError) as exc:
            raise SignatureError(f"{path}: not a readable PEM private key ({exc})") from None
        if not isinstance(priv, ed25519.Ed25519PrivateKey):
            raise SignatureError(f"{path}: not an Ed25519 key (make one with `evcal keygen`)")
        raw = priv.public_key().public_bytes(serialization.Encoding.Raw,
                                             serialization.PublicFormat.Raw)
        return cls(instance, priv, key_id(raw), raw)

    def attachment(self, key: str, payload: bytes) -> bytes:
        body: dict[str, Any] = {"v": 1, "instance": self.instance}
        if self.private is not None:
            body["key_id"] = self.key_id
            body["sig"] = self.private.sign(_message(self.instance, key, payload))
            body["pub"] = self.public_raw
        packed: bytes = msgpack.packb(body, use_bin_type=True)
        return packed


def read_attachment(attachment: bytes | None) -> dict[str, Any]:
    """The fields of an attachment ({} when there is none or it is not ours)."""
    if not attachment:
        return {}
    try:
        body = msgpack.unpackb(attachment, raw=False)
    except Exception:  # noqa: BLE001 - a foreign attachment
        return {}
    return body if isinstance(body, dict) and body.get("v") == 1 else {}


class Verifier:
    """Checks calibration attachments against one public key (a PEM file's, or raw bytes
    with :meth:`from_raw`)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        serialization, ed25519 = _crypto()
        try:
            pub = serialization.load_pem_public_key(Path(path).read_bytes())
        except (OSError, ValueError, TypeError) as exc:
            raise SignatureError(f"{path}: not a readable PEM public key ({exc})") from None
        if not isinstance(pub, ed25519.Ed25519PublicKey):
            raise SignatureError(f"{path}: not an Ed25519 public key")
        self._use(pub)

    @classmethod
    def from_raw(cls, raw: bytes) -> Verifier:
        """A verifier of the raw 32-byte Ed25519 public key ``raw``."""
        _, ed25519 = _crypto()
        try:
            pub = ed25519.Ed25519PublicKey.from_public_bytes(raw)
        except (ValueError, TypeError) as exc:
            raise SignatureError(f"not a raw Ed25519 public key ({exc})") from None
        self = cls.__new__(cls)
        self._use(pub)
        return self

    def _use(self, pub: Any) -> None:
        serialization, _ = _crypto()
        self._pub = pub
        self.public_raw: bytes = pub.public_bytes(serialization.Encoding.Raw,
                                                  serialization.PublicFormat.Raw)
        self.key_id = key_id(self.public_raw)

    def verify(self, key: str, payload: bytes, attachment: bytes | None) -> str:
        """The signing instance's name, or :class:`SignatureError` saying why not."""
        body = read_attachment(attachment)
        sig, instance = body.get("sig"), body.get("instance")
        if not isinstance(sig, bytes) or not isinstance(instance, str):
            raise SignatureError(f"the answer on {key} is not signed")
        if body.get("key_id") != self.key_id:
            raise SignatureError(f"the answer on {key} is signed with key "
                                 f"{body.get('key_id')!r}, not with {self.key_id}")
        from cryptography.exceptions import InvalidSignature

        try:
            self._pub.verify(sig, _message(instance, key, payload))
        except InvalidSignature:
            raise SignatureError(f"the signature of the answer on {key} (instance "
                                 f"{instance!r}) does not match its bytes") from None
        return instance


def default_known_services() -> Path:
    """Where ``evcal query`` pins service keys: ``$XDG_STATE_HOME/evcal/known_services``
    (``~/.local/state/evcal/known_services`` when the variable is unset)."""
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(Path.home(), ".local", "state")
    return Path(base) / "evcal" / "known_services"


class KnownServices:
    """The service keys a client has pinned, one per key prefix (trust on first use).

    A JSON file ``{"<prefix>": {"key": "<base64 raw Ed25519 key>", "key_id": ..., "instance":
    ..., "first_seen": ...}}``. Pinned per prefix, not per instance: an instance's name is
    whatever the answer says (a zenoh id by default, new at each start), while the key is the
    service's (``serve --sign-key``, shared by its workers). Delete an entry to accept a new
    key after replacing the service's on purpose.
    """

    def __init__(self, path: str | os.PathLike[str] | None = None) -> None:
        self.path = Path(path) if path is not None else default_known_services()

    def _read(self) -> dict[str, Any]:
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return {}
        except OSError as exc:
            raise SignatureError(f"{self.path}: cannot read the pinned service keys ({exc})"
                                 ) from None
        try:
            doc = json.loads(text)
        except ValueError as exc:
            raise SignatureError(f"{self.path}: not JSON ({exc}); fix or delete it") from None
        if not isinstance(doc, dict):
            raise SignatureError(f"{self.path}: a JSON {type(doc).__name__}, expected an "
                                 "object of pinned keys; fix or delete it")
        return doc

    def get(self, prefix: str) -> Verifier | None:
        """A verifier of the key pinned for ``prefix``, or None."""
        entry = self._read().get(prefix)
        if entry is None:
            return None
        try:
            raw = base64.b64decode(entry["key"], validate=True)
        except (KeyError, TypeError, ValueError) as exc:
            raise SignatureError(f"{self.path}: the entry for prefix {prefix!r} has no valid "
                                 f"key ({exc}); fix or delete it") from None
        return Verifier.from_raw(raw)

    def pin(self, prefix: str, verifier: Verifier, instance: str) -> None:
        """Record ``verifier``'s key for ``prefix`` (atomically; the folder private)."""
        doc = self._read()
        doc[prefix] = {
            "key": base64.b64encode(verifier.public_raw).decode(), "key_id": verifier.key_id,
            "instance": instance,
            "first_seen": datetime.datetime.now(datetime.timezone.utc).isoformat(
                timespec="seconds"),
        }
        self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        fd, tmp = tempfile.mkstemp(prefix=self.path.name + ".", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w") as f:
                f.write(json.dumps(doc, indent=2) + "\n")
            os.replace(tmp, self.path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
