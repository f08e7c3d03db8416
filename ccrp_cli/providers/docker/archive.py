"""In-memory tar archives for the Docker API's put_archive."""

from __future__ import annotations

import io
import tarfile
import time


def tar_files(files: list[tuple[str, bytes, int]], make_dirs: bool = False) -> bytes:
    """files: (path relative to the extraction point, content, mode), owned by root.

    make_dirs adds entries for parent directories (0755); leave it off when extracting into
    directories whose modes must stay as they are.
    """
    buf = io.BytesIO()
    now = time.time()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        dirs: set[str] = set()
        for path, content, mode in files:
            parts = path.split("/")[:-1]
            for i in range(1, len(parts) + 1 if make_dirs else 1):
                d = "/".join(parts[:i])
                if d not in dirs:
                    dirs.add(d)
                    info = tarfile.TarInfo(d)
                    info.type, info.mode, info.mtime = tarfile.DIRTYPE, 0o755, now
                    tar.addfile(info)
            info = tarfile.TarInfo(path)
            info.size, info.mode, info.mtime = len(content), mode, now
            tar.addfile(info, io.BytesIO(content))
    return buf.getvalue()
