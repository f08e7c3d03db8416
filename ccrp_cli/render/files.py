"""A file ccrp puts on a clone or in a robot's bundle: what every renderer returns and every
transport pushes. Its own module, so commands that only name files (status, knowledge, the API
manager's push) need not import the renderers, their templates and the PKI."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

from ..models.layout import SECRETS_DIR


@dataclass(frozen=True)
class BundleFile:
    name: str
    content: str
    mode: int
    dest: str | None = None  # absolute path on the target, for pushed bundles
    group: str = "root"


def applied_marker(files: list):
    """The file pushed after `files` once their groups are set and the units restarted. A run
    killed between copying the files and restarting OpenVPN (which starts only when its key is
    there) leaves files that match and a server that never started: without the marker the next
    run took them for done, and the clone failed `not serving` on every run after."""
    listing = "".join(f"{f.dest} {f.group} {f.mode:o} {hashlib.sha256(f.content.encode()).hexdigest()}\n" for f in files)
    return BundleFile(".applied", hashlib.sha256(listing.encode()).hexdigest() + "\n", 0o600, f"{SECRETS_DIR}/.applied")
