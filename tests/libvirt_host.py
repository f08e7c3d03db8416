"""Whether this machine can run VM clones for the tests that boot them (tests/e2e/test_libvirt.py,
the libvirt scenario): they take minutes of QEMU each (TCG here: no vmx/svm), so they are opt-in."""

from __future__ import annotations

import os

URI = "qemu:///system"


def gate() -> str | None:
    """None when libvirt VM tests may run here, else why not (a skip reason)."""
    if os.environ.get("CCRP_E2E_LIBVIRT") != "1":
        return "set CCRP_E2E_LIBVIRT=1 to boot VM clones (needs libvirtd: scripts/libvirt.sh)"
    try:
        import libvirt
    except ImportError:
        return "the libvirt binding is not installed (pip extra libvirt: scripts/libvirt.sh)"
    libvirt.registerErrorHandler(lambda _c, _e: None, None)
    try:
        libvirt.open(URI).close()
    except libvirt.libvirtError as exc:
        return f"libvirtd does not answer on {URI}: {exc}"
    return None
