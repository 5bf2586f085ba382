"""Ed25519 signatures on what may move a breaker: islanding decisions, arm/disarm requests, islanding requests.

The PyPI ROS 2 wheels ship Fast DDS without its security plugins, so SROS2 cannot authenticate anyone on the
domain. Instead, in the spirit of IEC 62351-6 (signed GOOSE), the messages that matter carry a signature
that breaker_command checks with public keys only: the partitioning node signs decisions with its private
key and an operator signs arm/disarm requests with another. A breaker node that is compromised can therefore
not forge either. Each signature covers a canonical encoding of every field the breaker node acts on, plus a
domain tag (so a decision signature can never pass as an arm signature) and the fields that defeat replay:
the decision id with the request stamp, or the nonce with the stamp of an arm request.

The stability monitor signs its islanding requests with a third key, so that partitioning can tell its request
from a forged one (which it refuses, saying why); an operator's request may stay unsigned, the paper's mode.

Keys never enter the repository: `controlled-islanding keys init DIR` makes them, private keys 0600.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from cryptography.hazmat.primitives.serialization import (
    Encoding,
    NoEncryption,
    PrivateFormat,
    PublicFormat,
    load_pem_private_key,
    load_pem_public_key,
)

from controlled_islanding import atomic

# Who signs what: the decision maker (partitioning), the operator who arms and disarms (and may sign requests),
# and the stability monitor that requests islanding.
ROLES = ('partitioning', 'operator', 'monitor')
DECISION_DOMAIN = 'controlled_islanding/IslandingDecision/v2'  # v2: the remedial actions too
ARM_DOMAIN = 'controlled_islanding/SetArmed/v1'
REQUEST_DOMAIN = 'controlled_islanding/IslandingRequest/v1'
SIGNATURE_BYTES = 64


class SigningError(ValueError):
    """A key or a signature that cannot be used; `reason` is the diagnostics key."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


def default_key_dir() -> Path:
    """Return `$CONTROLLED_ISLANDING_KEYS`, else `$XDG_CONFIG_HOME/controlled_islanding/keys` (~/.config/...)."""
    explicit = os.environ.get('CONTROLLED_ISLANDING_KEYS')
    if explicit:
        return Path(explicit)
    config = os.environ.get('XDG_CONFIG_HOME') or str(Path.home() / '.config')
    return Path(config) / 'controlled_islanding' / 'keys'


@dataclass(frozen=True)
class KeyPaths:
    """Where one role's key pair lives."""

    private: Path
    public: Path


def key_paths(directory: str | Path, role: str) -> KeyPaths:
    """Return the private (`<role>.key`) and public (`<role>.pub`) key files of a role in a directory."""
    if role not in ROLES:
        raise SigningError('bad_key', f'unknown key role {role!r}; roles are {", ".join(ROLES)}')
    base = Path(directory)
    return KeyPaths(base / f'{role}.key', base / f'{role}.pub')


def init_keys(directory: str | Path, force: bool = False) -> dict[str, KeyPaths]:
    """Make one Ed25519 key pair per role; keep existing pairs unless `force`.

    The directory is made 0700 and each private key is written 0600 through a temporary file renamed into
    place, so no reader ever sees a half-written or world-readable key.

    Returns:
        Role -> key files.

    """
    import fcntl

    base = Path(directory)
    base.mkdir(parents=True, exist_ok=True, mode=0o700)
    os.chmod(base, 0o700)
    made = {}
    # Processes started together on a fresh directory (replay's regression run, two graphs at once) each found a
    # role's pair missing and wrote their own: one's private key beside the other's public key, a pair that
    # signs nothing its verifier accepts (a clean-clone CI run: every later arming refused as unknown_key).
    with open(base / '.init.lock', 'w') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        for role in ROLES:
            paths = key_paths(base, role)
            made[role] = paths
            if paths.private.exists() and paths.public.exists() and not force:
                continue
            key = Ed25519PrivateKey.generate()
            atomic.write_bytes(paths.private, key.private_bytes(Encoding.PEM, PrivateFormat.PKCS8, NoEncryption()),
                               0o600)
            atomic.write_bytes(paths.public,
                               key.public_key().public_bytes(Encoding.PEM, PublicFormat.SubjectPublicKeyInfo), 0o644)
    return made


def load_private_key(path: str | Path) -> Ed25519PrivateKey:
    """Read a PEM Ed25519 private key that only its owner can read.

    Raises:
        SigningError: reason 'bad_key': missing, readable by group or others, or not an Ed25519 key.

    """
    path = Path(path)
    try:
        mode = path.stat().st_mode
        data = path.read_bytes()
    except OSError as exc:
        raise SigningError('bad_key', f'private key {path}: {exc.strerror or exc}') from exc
    if stat.S_IMODE(mode) & 0o077:
        raise SigningError('bad_key', f'private key {path} is readable by others (mode {stat.S_IMODE(mode):o}); '
                                      f'chmod 600 it')
    try:
        key = load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as exc:
        raise SigningError('bad_key', f'private key {path}: not a PEM private key ({exc})') from exc
    if not isinstance(key, Ed25519PrivateKey):
        raise SigningError('bad_key', f'private key {path}: not an Ed25519 key')
    return key


def load_public_key(path: str | Path) -> Ed25519PublicKey:
    """Read a PEM Ed25519 public key.

    Raises:
        SigningError: reason 'bad_key': missing or not an Ed25519 public key.

    """
    path = Path(path)
    try:
        key = load_pem_public_key(path.read_bytes())
    except OSError as exc:
        raise SigningError('bad_key', f'public key {path}: {exc.strerror or exc}') from exc
    except (ValueError, TypeError) as exc:
        raise SigningError('bad_key', f'public key {path}: not a PEM public key ({exc})') from exc
    if not isinstance(key, Ed25519PublicKey):
        raise SigningError('bad_key', f'public key {path}: not an Ed25519 key')
    return key


def fingerprint(key: Ed25519PublicKey | Ed25519PrivateKey) -> str:
    """Return a key's id: the first 16 hex digits of the SHA-256 of its raw public key."""
    public = key.public_key() if isinstance(key, Ed25519PrivateKey) else key
    return hashlib.sha256(public.public_bytes(Encoding.Raw, PublicFormat.Raw)).hexdigest()[:16]


def _canonical(domain: str, fields: dict) -> bytes:
    return json.dumps({'domain': domain, **fields}, sort_keys=True, separators=(',', ':'),
                      allow_nan=True).encode()


def _stamp_ns(stamp: object) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def decision_payload(msg: object) -> bytes:
    """Return the bytes a decision's signature covers: every field breaker_command reads or audits."""
    return _canonical(DECISION_DOMAIN, {
        'decision_id': str(msg.decision_id), 'request_id': str(msg.request_id),
        'request_stamp_ns': _stamp_ns(msg.request_stamp), 'status': int(msg.status), 'split': bool(msg.split),
        'bus_numbers': [int(x) for x in msg.bus_numbers], 'bus_island': [int(x) for x in msg.bus_island],
        'cut_branch_ids': [str(x) for x in msg.cut_branch_ids], 'cut_from_bus': [int(x) for x in msg.cut_from_bus],
        'cut_to_bus': [int(x) for x in msg.cut_to_bus], 'shed_bus': [int(x) for x in msg.shed_bus],
        'shed_mw': [float(x) for x in msg.shed_mw], 'trip_generator_names': [str(x) for x in msg.trip_generator_names],
        'key_id': str(msg.key_id)})


def arm_payload(request: object, target: str) -> bytes:
    """Return the bytes an arm/disarm request's signature covers; `target` is the breaker node's full name."""
    return _canonical(ARM_DOMAIN, {'target': target, 'action': int(request.action),
                                   'stamp_ns': _stamp_ns(request.stamp), 'nonce': str(request.nonce),
                                   'key_id': str(request.key_id)})


def request_payload(msg: object) -> bytes:
    """Return the bytes an islanding request's signature covers: every field partitioning and coherency read."""
    return _canonical(REQUEST_DOMAIN, {
        'request_id': str(msg.request_id), 'stamp_ns': _stamp_ns(msg.header.stamp), 'reason': str(msg.reason),
        'branch_changes_before': int(msg.branch_changes_before),
        'generator_names': [str(x) for x in msg.generator_names], 'group': [int(x) for x in msg.group],
        'predicted_first_slip_ns': _stamp_ns(msg.predicted_first_slip), 'key_id': str(msg.key_id)})


def sign_request(msg: object, key: Ed25519PrivateKey) -> object:
    """Sign an IslandingRequest (rclpy or rosbags type) in place with a requester's key; return it."""
    msg.key_id = fingerprint(key)
    msg.signature = sign(key, request_payload(msg))
    return msg


def check_request(msg: object, keys: dict[str, Ed25519PublicKey], require_signed: bool) -> str | None:
    """Return why an islanding request is not authentic, or None when it is (or may be unsigned).

    Args:
        msg: The IslandingRequest.
        keys: Key id -> public key of each requester whose signature is accepted.
        require_signed: Whether an unsigned request is refused too (else it is an operator's, the paper's mode).

    """
    if not bytes(msg.signature) and not str(msg.key_id):
        return 'the request is unsigned and require_signed_requests is set' if require_signed else None
    key = keys.get(str(msg.key_id))
    if key is None:
        return f'the request is signed with key {str(msg.key_id)[:32]!r}, which is no requester key held here'
    try:
        verify(key, request_payload(msg), msg.signature)
    except SigningError as exc:
        return f'the request signature: {exc}'
    return None


def sign(key: Ed25519PrivateKey, payload: bytes) -> list[int]:
    """Return the signature of a payload as the list of byte values a uint8[] field takes."""
    return list(key.sign(payload))


def verify(key: Ed25519PublicKey, payload: bytes, signature: object) -> None:
    """Check a signature.

    Raises:
        SigningError: reason 'unsigned' (no signature) or 'bad_signature'.

    """
    raw = bytes(signature)
    if not raw:
        raise SigningError('unsigned', 'no signature; breaker_command acts only on signed messages')
    if len(raw) != SIGNATURE_BYTES:
        raise SigningError('bad_signature', f'signature has {len(raw)} bytes, an Ed25519 signature has 64')
    try:
        key.verify(raw, payload)
    except InvalidSignature as exc:
        raise SigningError('bad_signature', 'signature does not verify with the configured public key') from exc


def signed_arm_request(request: object, key: Ed25519PrivateKey, target: str, arm: bool, now_s: float) -> object:
    """Fill and sign a SetArmed request (rclpy or rosbags type) for the breaker node named `target`.

    Args:
        request: An empty SetArmed.Request.
        key: The operator's private key.
        target: The breaker node's fully qualified name, e.g. '/breaker_command'.
        arm: True to arm, False to disarm.
        now_s: Wall-clock time, s since the epoch.

    """
    request.action = 1 if arm else 2  # SetArmed.Request.ACTION_ARM / ACTION_DISARM
    request.stamp.sec, request.stamp.nanosec = int(now_s), int((now_s % 1) * 1e9)
    request.nonce = os.urandom(16).hex()
    request.key_id = fingerprint(key)
    request.signature = sign(key, arm_payload(request, target))
    return request
