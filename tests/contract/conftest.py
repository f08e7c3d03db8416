"""The provider contract suite runs once per backend whose harness module exists."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

KINDS = ("docker", "aws", "openstack", "gcp", "memory", "libvirt")
AVAILABLE = [k for k in KINDS if (Path(__file__).parent / f"harness_{k}.py").exists()]


@pytest.fixture(params=AVAILABLE)
def harness(request, tmp_path):
    module = importlib.import_module(f"tests.contract.harness_{request.param}")
    with module.make_harness(tmp_path) as h:
        yield h
