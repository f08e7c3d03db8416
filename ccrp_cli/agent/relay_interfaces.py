"""The relay agent's loader of the workspace's ROS 2 message types (docs/workloads.md, ROS 2
interface packages), imported by relay_ros2.py when a type is not the distro's. `fleet up` pushes
it beside the relay (services/sharing.py): only a clone made from a snapshot has a workspace, and a
bare clone's user-data has no room for it."""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import json
import os
import re

from relay import log


class SourceOnlyLoader(importlib.machinery.SourceFileLoader):
    """A module's source, compiled each time: no bytecode read or written (its stats unknown)."""

    def path_stats(self, path):
        raise OSError("bytecode not used")

    def set_data(self, path, data, *, _mode=0o666):
        pass


class WorkspaceInterfaces(importlib.abc.MetaPathFinder):
    """The message code ccrp generated from the workspace's interface packages (.msg, .srv,
    .action; templates/image/interfaces-build.sh), and nothing else of the workspace: the relay
    holds the clone's relay key, and the workspace is the user's code (ros-run never gives it to
    ccrp's agents). A package is found here only when the distro has none of its name (this finder
    comes after the others), only if the build's list (share/ccrp/interfaces.json) names it, and
    only if its directory holds exactly the files listed, each with its digest: a module a Python
    package of the workspace put beside them (an extension module is loaded before a .py of the
    same name) refuses the whole package. Its libraries, checked the same way, are loaded
    by their paths first, so that its extension modules find them without the workspace's lib/ on
    the loader's path (LD_LIBRARY_PATH, which would offer every library there to the relay)."""

    ROOT = "/opt/ccrp/workspace"
    _installed: WorkspaceInterfaces | None = None

    def __init__(self, root: str) -> None:
        self.root = root
        # package -> its site directory, None when refused: checked once per process, as the modules
        # it imported stay loaded (a deploy that changes them restarts the relay: install_space.py).
        self.checked: dict[str, str | None] = {}

    @classmethod
    def install(cls) -> WorkspaceInterfaces:
        """The finder, last on the import path (once per process)."""
        import sys

        if cls._installed is None or cls._installed not in sys.meta_path:
            cls._installed = cls(cls.ROOT)
            sys.meta_path.append(cls._installed)
        return cls._installed

    def manifest(self) -> dict:
        try:
            with open(os.path.join(self.root, "share", "ccrp", "interfaces.json"), encoding="utf-8") as f:
                data = json.load(f)
        except (OSError, ValueError):
            return {}
        return data if isinstance(data, dict) and isinstance(data.get("packages"), dict) else {}

    def find_spec(self, fullname: str, path=None, target=None):
        if "." in fullname or path is not None:
            return None  # a submodule: its package's own __path__ finds it
        if fullname not in self.checked:
            self.check(fullname)
        site = self.checked.get(fullname)
        if site is None:
            return None
        # Its modules read from their sources only: a .pyc in a __pycache__ beside them (written by
        # whoever imported them as root, or put there) would run in place of the checked .py. The
        # import system asks the finder cached for a directory first, for the package's modules too.
        import sys

        loaders = [(importlib.machinery.ExtensionFileLoader, importlib.machinery.EXTENSION_SUFFIXES),
                   (SourceOnlyLoader, importlib.machinery.SOURCE_SUFFIXES)]
        for d, _, _ in os.walk(os.path.join(site, fullname)):
            if os.path.basename(d) != "__pycache__":
                sys.path_importer_cache[d] = importlib.machinery.FileFinder(d, *loaders)
        sys.path_importer_cache[site] = importlib.machinery.FileFinder(site, *loaders)
        return importlib.machinery.PathFinder.find_spec(fullname, [site])

    def check(self, package: str) -> None:
        """When the build listed `package`: every listed package checked (one may use another's
        messages, and its libraries those of the other), the libraries of those as listed loaded,
        each package's site directory (or None, logged) put in self.checked."""
        import ctypes

        data = self.manifest()
        listed = data.get("packages", {})
        if package not in listed:
            self.checked[package] = None
            return
        site = os.path.join(self.root, str(data.get("site", "")))
        good = {name: files for name, files in listed.items() if self._as_built(name, files, site)}
        libs = [os.path.join(self.root, rel) for files in good.values() for rel in files if rel.startswith("lib/lib")]
        while libs:  # in an order that works: each pass loads those whose dependencies are in
            left = []
            for lib in sorted(libs):
                try:
                    ctypes.CDLL(lib, mode=ctypes.RTLD_GLOBAL)
                except OSError:
                    left.append(lib)
            if len(left) == len(libs):
                for lib in left:
                    name = os.path.basename(lib)[3:].split("__", 1)[0]
                    if good.pop(name, None) is not None:
                        log(f"workspace interfaces: {name} not loaded: {os.path.basename(lib)} does not load")
                break
            libs = left
        for name in listed:
            self.checked[name] = site if name in good else None
            if name in good:
                log(f"workspace interfaces: {name} loaded from {os.path.join(site, name)}")

    def _as_built(self, package: str, files, site: str) -> bool:
        """Whether `package`'s directory holds exactly the files the build listed, each with its
        digest (its __pycache__ aside: never read), and its listed libraries are as built."""
        import hashlib

        pkg_dir = os.path.join(site, package)
        if not (isinstance(files, dict) and files and re.fullmatch(r"[a-z][a-z0-9_]*", package)):
            return False
        listed = {os.path.normpath(os.path.join(self.root, str(rel))): str(digest) for rel, digest in files.items()}
        lib = re.compile(re.escape(os.path.join(self.root, "lib", f"lib{package}__")) + r"[a-z0-9_]+\.so")
        outside = [p for p in listed if not (p.startswith(pkg_dir + os.sep) or lib.fullmatch(p))]
        if outside:  # the list is the build's, in the install space: only its own files are read
            log(f"workspace interfaces: {package} not loaded: the build's list names {outside[0]}")
            return False
        found = {os.path.join(d, f) for d, _, names in os.walk(pkg_dir) for f in names if os.path.basename(d) != "__pycache__"}
        extra = sorted(found - set(listed))
        if extra:
            log(f"workspace interfaces: {package} not loaded: {extra[0]} was not generated by ccrp's build")
            return False
        for path, digest in listed.items():
            try:
                with open(path, "rb") as f:
                    same = hashlib.sha256(f.read()).hexdigest() == digest
            except OSError:
                same = False
            if not same:
                log(f"workspace interfaces: {package} not loaded: {path} is not the file ccrp's build generated")
                return False
        return True
