"""Whether this machine can run VM clones for the tests that boot them.

- `tests/e2e/test_libvirt.py` (two VM clones, a simulated robot, a shared topic; TCG here since this
  CPU shows no vmx/svm) and the provider contract suite on libvirt (tests/contract/harness_libvirt.py:
  tiny VMs) run wherever libvirtd answers on qemu:///system with the binding installed
  (scripts/libvirt.sh sets both up; .ci/run runs it), so the README's test command runs them in CI.
- The user-path scenario on libvirt (tests/scenarios, about 25 minutes of VM boots) only when asked:
  CCRP_E2E_LIBVIRT=1.
- CCRP_E2E_LIBVIRT=0 turns both off."""

from __future__ import annotations

import os

URI = "qemu:///system"


def gate(scenario: bool = False) -> str | None:
    """None when these libvirt VM tests may run here, else why not (a skip reason)."""
    switch = os.environ.get("CCRP_E2E_LIBVIRT", "")
    if switch == "0":
        return "CCRP_E2E_LIBVIRT=0: no VM clones"
    if scenario and switch != "1":
        return "set CCRP_E2E_LIBVIRT=1 for the user-path scenario on VM clones (about 25 minutes of boots)"
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
