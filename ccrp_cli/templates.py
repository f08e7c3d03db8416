"""One Jinja2 environment for every text template (strict: an undefined name is an error)."""

from __future__ import annotations

from functools import cache
from typing import Any

import jinja2

from .resources import data_dir


@cache
def _env() -> jinja2.Environment:
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(data_dir("templates"))),
        undefined=jinja2.StrictUndefined,
        keep_trailing_newline=True,
        autoescape=False,  # noqa: S701 - config files, not HTML
    )


def render(name: str, **ctx: Any) -> str:
    return _env().get_template(name).render(**ctx)


def static(name: str) -> str:
    """A template file used verbatim (scripts, units without parameters)."""
    return (data_dir("templates") / name).read_text()
