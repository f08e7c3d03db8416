"""Shared secrets besides certificates: tls-crypt keys and the VPN password (second factor)."""

from __future__ import annotations

import base64
import hashlib
import hmac
import secrets

# scrypt parameters; the clone's auth script (templates/clone/ccrp-auth) reads them from the hash.
# Passwords are 192 random bits (new_password), so the hash only has to make a leaked `passwd`
# file useless, not slow down guessing: a light scrypt (1 MiB, ~2 ms) keeps 100 robots fast.
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**10, 8, 1


def tls_crypt_key() -> str:
    """A 2048-bit OpenVPN "Static key V1", the format `openvpn --genkey tls-crypt` writes."""
    raw = secrets.token_bytes(256).hex()
    lines = [raw[i : i + 32] for i in range(0, len(raw), 32)]
    return (
        "#\n# 2048 bit OpenVPN static key\n#\n-----BEGIN OpenVPN Static key V1-----\n"
        + "\n".join(lines)
        + "\n-----END OpenVPN Static key V1-----\n"
    )


def new_password() -> str:
    return secrets.token_urlsafe(24)


def hash_password(password: str, salt: bytes | None = None) -> str:
    salt = salt or secrets.token_bytes(16)
    digest = hashlib.scrypt(password.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P, dklen=32)
    b64 = lambda b: base64.b64encode(b).decode()  # noqa: E731
    return f"$scrypt$n={SCRYPT_N},r={SCRYPT_R},p={SCRYPT_P}${b64(salt)}${b64(digest)}"


def verify_password(password: str, encoded: str) -> bool:
    try:
        _, scheme, params, salt_b64, digest_b64 = encoded.split("$")
        opts = dict(kv.split("=") for kv in params.split(","))
        salt, want = base64.b64decode(salt_b64), base64.b64decode(digest_b64)
        got = hashlib.scrypt(
            password.encode(), salt=salt, n=int(opts["n"]), r=int(opts["r"]), p=int(opts["p"]), dklen=len(want)
        )
    except (ValueError, KeyError):
        return False
    return scheme == "scrypt" and hmac.compare_digest(got, want)
