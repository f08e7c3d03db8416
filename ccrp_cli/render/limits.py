"""User-data size limits per provider (each provider's ProviderInfo), checked before any API call."""

from __future__ import annotations

import gzip

from ..errors import CcrpError
from ..providers import info


def fit_user_data(provider: str, text: str) -> tuple[bytes, bool]:
    """The payload to send and whether it is gzipped; an error when it cannot fit."""
    limit, gzip_ok = info(provider).user_data_limit, info(provider).user_data_gzip
    raw = text.encode()
    if len(raw) <= limit:
        return raw, False
    if gzip_ok:
        packed = gzip.compress(raw, mtime=0)
        if len(packed) <= limit:
            return packed, True
    raise CcrpError(
        f"cloud-init user-data is {len(raw)} bytes, over {provider}'s limit of {limit} bytes"
        + (" even gzipped" if gzip_ok else ""),
        hint="share fewer topics per robot or move large files into the snapshot",
    )
