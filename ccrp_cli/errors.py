"""Every user-facing failure is a CcrpError: a code (exit status), one-line message and a hint."""

from __future__ import annotations

# Exit codes (README: Commands).
OK = 0
FAILED = 1
BAD_INPUT = 2
PARTIAL = 3


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
        return text


class InputError(CcrpError):
    """Bad input: inventory, names, options. Exit code 2; nothing was changed."""

    def __init__(self, message: str, *, hint: str | None = None) -> None:
        super().__init__(message, hint=hint, code=BAD_INPUT)
