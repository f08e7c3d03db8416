"""How files and commands reach a clone: SSH with pinned host keys (clouds), the Docker API (local)."""
