"""`ccrp` run inside the test process, for backends whose fake lives there (the GCE fake's clients
are autospecced mocks, which no other process can reach).

The user's argv goes through the console entry point itself (ccrp_cli.cli.main.run: the same
parsing, error lines and exit codes as `python -m ccrp_cli`), with the shell's environment given
for the call (CCRP_HOME...), stdout and stderr captured apart (messages on stderr, --json on
stdout), and patches that point the provider at the fake (e.g. Clients.connect). The answer is a
subprocess.CompletedProcess, so a scenario treats it like the subprocess it stands for.

One command at a time (a lock): sys.argv, sys.stdout, sys.stderr and os.environ are the process's.
A command that outlives `timeout` raises subprocess.TimeoutExpired as subprocess.run would, but it
cannot be killed: it goes on in its daemon thread (its output is lost) and the runner refuses
further commands until it ends.
"""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
import threading
import traceback
from collections.abc import Callable


class _Tee(io.TextIOBase):
    """A text stream that keeps what is written (one per command and stream)."""

    def __init__(self, echo=None) -> None:
        self.buf = io.StringIO()
        self.echo = echo
        self.lock = threading.Lock()

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        with self.lock:
            self.buf.write(text)
        if self.echo is not None:  # progress visible under `pytest -s`
            self.echo.write(text)
            self.echo.flush()
        return len(text)

    def isatty(self) -> bool:
        return False

    def getvalue(self) -> str:
        return self.buf.getvalue()


class InProcessCcrp:
    """Callable as Backend.runner: runner(*argv, timeout=...) -> CompletedProcess."""

    def __init__(self, env: dict[str, str], patches: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext,
                 echo_stderr: bool = False) -> None:
        self.env = env
        self.patches = patches
        self.echo_stderr = echo_stderr
        self._lock = threading.Lock()
        self._running: threading.Thread | None = None
        self.log: list[tuple[tuple[str, ...], int, float]] = []  # (argv, returncode, seconds) of each command

    def __call__(self, *args: str, timeout: float = 900) -> subprocess.CompletedProcess:
        import time

        with self._lock:
            if self._running is not None and self._running.is_alive():
                raise RuntimeError(f"an earlier ccrp command is still running in this process ({self._running.name})")
            argv = ["ccrp", *args]
            out, err = _Tee(), _Tee(sys.__stderr__ if self.echo_stderr else None)
            result: dict[str, int] = {}

            def main() -> None:
                from ccrp_cli.cli.main import run

                try:
                    run()
                except SystemExit as exc:
                    code = exc.code
                    if code is None:
                        result["rc"] = 0
                    elif isinstance(code, int):
                        result["rc"] = code
                    else:  # sys.exit("message"): Python prints it and exits 1
                        print(code, file=sys.stderr)
                        result["rc"] = 1
                except BaseException:  # noqa: BLE001 - a crash: the traceback and exit 1, as Python does
                    traceback.print_exc(file=sys.stderr)
                    result["rc"] = 1
                else:
                    result["rc"] = 0

            env = {**self.env}
            saved_env = dict(os.environ)
            saved = sys.argv, sys.stdout, sys.stderr
            t0 = time.monotonic()
            thread = threading.Thread(target=main, name=f"ccrp {' '.join(args[:3])}", daemon=True)
            with self.patches():
                os.environ.pop("CCRP_INVENTORY", None)
                os.environ.update(env)
                sys.argv, sys.stdout, sys.stderr = argv, out, err
                try:
                    thread.start()
                    thread.join(timeout)
                finally:
                    sys.argv, sys.stdout, sys.stderr = saved
                    os.environ.clear()
                    os.environ.update(saved_env)
            if thread.is_alive():
                self._running = thread
                raise subprocess.TimeoutExpired(argv, timeout, output=out.getvalue(), stderr=err.getvalue())
            self.log.append((tuple(args), result["rc"], time.monotonic() - t0))
            return subprocess.CompletedProcess(argv, result["rc"], out.getvalue(), err.getvalue())
