"""How files and commands reach a clone: SSH with pinned host keys (clouds), the Docker API (local)."""

# The most one exec on a clone may answer. The clone chooses what it writes: a clone that floods
# stdout must not fill the operator's memory (a `ccrp status` reads every clone at once), so the
# transports (ssh.py, providers/docker/client.py) stop reading past this and fail the command. The
# largest answer ccrp asks for is a knowledge item (services/knowledge.py MAX_ITEM, 64 MiB) in base64,
# 85.3 MiB; the reads of logs, status and a relay's drain are far smaller.
EXEC_OUTPUT_MAX = 96 << 20


def too_much(command: str, where: str) -> str:
    """The one line of an exec whose output went past EXEC_OUTPUT_MAX."""
    return f"`{command[:120]}` on {where} wrote over {EXEC_OUTPUT_MAX >> 20} MiB; ccrp stopped reading it"
