"""A file ccrp puts on a clone or in a robot's bundle: what every renderer returns and every
transport pushes. Its own module, so commands that only name files (status, knowledge, the API
manager's push) need not import the renderers, their templates and the PKI."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BundleFile:
    name: str
    content: str
    mode: int
    dest: str | None = None  # absolute path on the target, for pushed bundles
    group: str = "root"
