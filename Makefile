# ccrp developer entry points. `make test` is the command CI runs (see README).
PY := .venv/bin/python

.PHONY: setup quickstart test unit quick bench clean

setup:
	bash scripts/setup.sh

quickstart:
	bash scripts/quickstart.sh

# Every test, slow end-to-end ones included, on 3 workers: the end-to-end modules mostly wait on
# boots and installs, so they overlap well on 2 cores (docs/benchmarks.md "Test suite"). Each
# module (and each scenario backend) stays on one worker, in file order; the 25 slowest are listed.
test:
	$(PY) -m pytest -n 3 --dist loadgroup --no-loadscope-reorder --durations=25

unit:
	$(PY) -m pytest tests/unit

# The development loop: unit and contract tests (no fleet, no boot), the input fuzzer at 100
# examples instead of 1000.
quick:
	CCRP_FUZZ_EXAMPLES=100 $(PY) -m pytest -n 3 --dist loadgroup tests/unit tests/contract

bench:
	$(PY) bench/startup.py
	$(PY) bench/render_fleet.py

clean:
	rm -rf .ccrp .pytest_cache
