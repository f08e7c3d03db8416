"""Every user-facing failure is a CcrpError: a code (exit status), one-line message and a hint.
failure() is the one translation of any exception into that, for the CLI (cli/main.py, and its
--json envelope) and the dashboard alike."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager

# Exit codes (README: Commands).
OK = 0
FAILED = 1
BAD_INPUT = 2
PARTIAL = 3
INTERRUPTED = 130  # Ctrl-C, as a shell reports it


class CcrpError(Exception):
    """A failure the user can understand and act on; rendered as one line on stderr."""

    def __init__(self, message: str, *, hint: str | None = None, code: int = FAILED) -> None:
        super().__init__(message)
        self.message = message
        self.hint = hint
        self.code = code

    def one_line(self) -> str:
        text = " ".join(self.message.split())
        if self.hint:
            text += f" (hint: {' '.join(self.hint.split())})"
        return printable(text)  # a message may hold a clone's output (a failed step's, its journal's)

    def envelope(self) -> dict:
        """What `--json` prints on stdout for a failure (README: Commands)."""
        return {"error": {"code": self.code, "message": " ".join(self.message.split()),
                          "hint": " ".join(self.hint.split()) if self.hint else None}}


class InputError(CcrpError):
    """Bad input: inventory, names, options. Exit code 2; nothing was changed."""

    def __init__(self, message: str, *, hint: str | None = None) -> None:
        super().__init__(message, hint=hint, code=BAD_INPUT)


class Interrupted(CcrpError):
    """Ctrl-C (or an aborted prompt): every step ccrp takes leaves its state on disk consistent."""

    def __init__(self) -> None:
        super().__init__("interrupted; state on disk is consistent, run the command again to continue",
                         code=INTERRUPTED)


def failure(exc: BaseException) -> CcrpError:
    """Any exception as the failure a user is shown: a CcrpError as it is, Ctrl-C as Interrupted,
    anything else (a bug, an SDK's own error) as its type and text with exit code 1. The CLI lets
    the last kind end in a traceback; the dashboard, which goes on, shows it in one line."""
    if isinstance(exc, CcrpError):
        return exc
    if isinstance(exc, KeyboardInterrupt):
        return Interrupted()
    return CcrpError(f"{type(exc).__name__}: {exc}")


@contextmanager
def translated(what: str, to_ccrp: Callable[[str, Exception], CcrpError | None]) -> Iterator[None]:
    """A backend's SDK failures leave it as one-line CcrpErrors (cause kept): `to_ccrp` makes one of
    an error of its SDK, and gives None for any other exception, which goes on as it is (a bug)."""
    try:
        yield
    except CcrpError:
        raise
    except Exception as exc:
        error = to_ccrp(what, exc)
        if error is None:
            raise
        raise error from exc


def one_line(exc: BaseException, limit: int | None = None) -> str:
    """failure(exc) in one line, cut to `limit` characters with an ellipsis."""
    text = failure(exc).one_line()
    return text if limit is None or len(text) <= limit else text[: limit - 1] + "…"


# A user's value echoed in an error is cut to this many characters: a 100k-character name must not
# become a 100k-character error line.
SHOWN_CHARS = 80


def shown(value: object, limit: int = SHOWN_CHARS) -> str:
    """repr() of a user's value for an error line, cut to `limit` characters with an ellipsis."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


# A clone's text (its journal, a command's output, its agents' reports) is the clone's to choose, and
# a node there is the user's code: on a terminal, ESC]52 writes the operator's clipboard, ESC[2J
# clears the screen, a CR or a newline inside one message forges a line of ccrp's own, and a lone
# U+009B is CSI to an 8-bit terminal. So every control character is shown as its escape: C0 (a tab
# only moves the cursor on, and stays), DEL and C1. A backslash stays as it is: text that spells
# `\x1b` shows the same as an escaped ESC, which is harmless and keeps paths and regexes readable.
# The bidirectional overrides and isolates (U+202A-202E, U+2066-2069), the marks and zero-width
# characters (U+200B-200F) and the BOM do not drive a terminal but reorder or hide what the operator
# reads (a line that shows as "ok" holds something else): escaped too, as `\u202e`.
_CONTROL = re.compile("[\x00-\x08\x0a-\x1f\x7f-\x9f\u200b-\u200f\u202a-\u202e\u2066-\u2069\ufeff]")
_NAMED = {"\n": "\\n", "\r": "\\r"}


def printable(text: str) -> str:
    """`text` safe for a terminal: each control character but tab as its escape (`\\x1b`, `\\n`).
    cli/output.py passes every line and table cell it writes through this, and one_line() does;
    --json keeps the exact text, which JSON encodes itself."""
    return _CONTROL.sub(lambda m: _NAMED.get(m.group()) or _escape(ord(m.group())), text)


def _escape(code: int) -> str:
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


class cannot_write:  # noqa: N801 - used as `with cannot_write(out):`
    """Turn an OSError while writing into `out` (a user's --out) into one line, exit 2."""

    def __init__(self, out: object) -> None:
        self.out = out

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind, exc, tb) -> bool:
        if isinstance(exc, (OSError, ValueError)) and not isinstance(exc, CcrpError):
            # ValueError: a NUL byte in the path. The failing path may be a parent of `out`.
            where = getattr(exc, "filename", None) or self.out
            reason = getattr(exc, "strerror", None) or str(exc)
            raise InputError(f"cannot write {shown(str(where))}: {reason}") from None
        return False
