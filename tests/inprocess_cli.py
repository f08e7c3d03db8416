"""`ccrp` run in the test process through its console entry point (ccrp_cli.cli.main.run), for
property tests that run it a thousand times: the same parsing, error lines and exit codes as
`python -m ccrp_cli`, without a Python start per example. An exception that escapes run() is not
caught here: it is what the user would see as a traceback, so the test fails with it."""

from __future__ import annotations

import contextlib
import io
import os
import sys
from pathlib import Path


def run_ccrp_inprocess(*args: str, home: Path, env: dict[str, str] | None = None,
                       err: io.StringIO | None = None) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of `ccrp ARGS` with CCRP_HOME=home and `env` set meanwhile;
    `err`: the stream stderr goes to (a StringIO's subclass that also shows it, for a benchmark)."""
    from ccrp_cli.cli.main import run

    out, err = io.StringIO(), err if err is not None else io.StringIO()
    changes = {"CCRP_HOME": str(home), **(env or {})}
    saved_argv, saved_env = sys.argv, {k: os.environ.get(k) for k in changes}
    sys.argv = ["ccrp", *args]
    os.environ.update(changes)
    code = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                run()
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.argv = saved_argv
        for key, value in saved_env.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
    return code, out.getvalue(), err.getvalue()
