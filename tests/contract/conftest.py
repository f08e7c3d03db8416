"""The provider contract suite runs once per backend whose harness module exists, and once per
variant: the parameter is the module's suffix, so `openstack_real` (the real cloud, opt-in) runs
the provider of kind `openstack` as `openstack` (the fake) does."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

KINDS = ("docker", "aws", "openstack", "gcp", "memory", "libvirt")
# Harnesses of a backend's provider on something other than its usual fake: {parameter: kind}.
VARIANTS = {"openstack_real": "openstack"}  # the real cloud of scripts/openstack.sh (opt-in)
AVAILABLE = [k for k in (*KINDS, *VARIANTS) if (Path(__file__).parent / f"harness_{k}.py").exists()]


@pytest.fixture(params=AVAILABLE)
def harness(request, tmp_path):
    module = importlib.import_module(f"tests.contract.harness_{request.param}")
    with module.make_harness(tmp_path) as h:
        yield h
