"""Whether this machine can run VM clones for the tests that boot them: `tests/e2e/test_libvirt.py`
(two VM clones, a simulated robot, a shared topic: about 15 minutes of QEMU beside the other tests,
TCG here since this CPU shows no vmx/svm) and the user-path scenario on libvirt (tests/scenarios,
about 25 minutes of VM boots). Both are opt-in (CCRP_E2E_LIBVIRT=1): the README's test command with
the first took 29.9 minutes here on Noetic and 30.4 on Jazzy (docs/benchmarks.md, runs 29 and 33)."""

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
        return "the libvirt binding is not installed (scripts/libvirt.sh installs it, with libvirtd)"
    libvirt.registerErrorHandler(lambda _c, _e: None, None)
    try:
        libvirt.open(URI).close()
    except libvirt.libvirtError as exc:
        return f"libvirtd does not answer on {URI} (start it: bash scripts/libvirt.sh): {exc}"
    return None
