# ccrp developer entry points. `make test` is the command CI runs (see README).
PY := .venv/bin/python

.PHONY: setup quickstart test unit quick bench clean openstack e2e-openstack-real e2e-openstack-real-gateway contract-openstack-real e2e-offload-ros1

setup:
	bash scripts/setup.sh

quickstart:
	bash scripts/quickstart.sh

# Every test, slow end-to-end ones included, on 3 workers: the end-to-end modules wait on boots and
# installs part of the time, and 3 workers keep 2 cores busy (docs/benchmarks.md "The test suite").
# Each module (and each scenario backend) stays on one worker, in file order; the 25 slowest are listed.
# Its temporary directory is short and fixed (pytest empties it at the start): paths in the one-line
# errors some tests compare are cut beyond a length, which pytest's default under xdist reached.
test:
	$(PY) -m pytest -n 3 --dist loadgroup --no-loadscope-reorder --durations=25 --basetemp=/tmp/ccrptest

unit:
	$(PY) -m pytest tests/unit

# The development loop: unit and contract tests (no fleet, no boot), the input fuzzer at 100
# examples instead of 1000.
quick:
	CCRP_FUZZ_EXAMPLES=100 $(PY) -m pytest -n 3 --dist loadgroup --basetemp=/tmp/ccrpquick tests/unit tests/contract

# The offloading example's ROS 1 fleet (C++ node, catkin) on Docker: fleet up, the robot's scan answered
# with a map, a changed C++ source deployed and rolled back (about 10 minutes: C++ builds). Not part of `make test`.
e2e-offload-ros1:
	CCRP_E2E_OFFLOAD_ROS1=1 $(PY) -m pytest tests/e2e/test_offload_ros1.py -v

# A real single-node OpenStack on this machine (docs/openstack.md), and ccrp's user path on it: init, bake,
# fleet up of two clones, a robot through its floating IP, a shared topic, deploy, stop/start, fleet
# down (about 45 minutes on 2 cores, 20 of them the bake: Nova emulates the guests' CPU). Not part of `make test`.
openstack:
	bash scripts/openstack.sh

e2e-openstack-real: openstack
	CCRP_E2E_OPENSTACK_REAL=1 $(PY) -m pytest -v -s --basetemp=/tmp/ccrp-osreal tests/e2e/test_openstack_real.py

# The same path with the fleet behind an entry gateway (provider.entry: gateway) and the project's
# floating-IP quota at 1: the gateway holds it, deleted and made again by `fleet up` (about 50 minutes).
e2e-openstack-real-gateway: openstack
	CCRP_E2E_OPENSTACK_REAL=1 CCRP_OPENSTACK_ENTRY=gateway $(PY) -m pytest -v -s --basetemp=/tmp/ccrp-osreal-gw tests/e2e/test_openstack_real.py

# The provider contract suite and the faults a real cloud causes (a quota of 1 instance, a missing flavor,
# an image deleted under the fleet, wrong credentials) on that OpenStack, with tiny busybox servers
# (docs/openstack.md "The provider contract on the real cloud"; about 10 minutes). Skips if the cloud
# does not answer (`make openstack` starts it). Not part of `make test`.
CONTRACT_OSREAL_TMP ?= /tmp/ccrp-contract-osreal
contract-openstack-real:
	CCRP_E2E_OPENSTACK_REAL=1 $(PY) -m pytest -k openstack_real -p no:warnings --durations=20 --basetemp=$(CONTRACT_OSREAL_TMP) tests/contract

bench:
	$(PY) bench/startup.py
	$(PY) bench/render_fleet.py

clean:
	rm -rf .ccrp .pytest_cache
