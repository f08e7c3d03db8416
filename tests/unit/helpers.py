"""Helpers shared by unit test modules (none of them a fixture: those are in conftest.py)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import types
from pathlib import Path

AGENT = Path(__file__).resolve().parents[2] / "ccrp_cli" / "agent" / "relay.py"


def openssl_verify(pki, cert, crl_check=False):
    args = ["openssl", "verify", "-CAfile", str(pki / "ca.crt")]
    if crl_check:
        args += ["-crl_check", "-CRLfile", str(pki / "crl.pem")]
    return subprocess.run([*args, str(cert)], capture_output=True, text=True)


def load_agent():
    """relay.py runs on a clone with rospy; its Zenoh config needs none of it."""
    stubs = {name: types.ModuleType(name) for name in ("rospy", "rosgraph") if name not in sys.modules}
    sys.modules.update(stubs)
    try:
        spec = importlib.util.spec_from_file_location("ccrp_relay_agent", AGENT)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        for name in stubs:
            sys.modules.pop(name, None)
