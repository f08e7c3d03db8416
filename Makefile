# ccrp developer entry points. `make test` is the command CI runs (see README).
PY := .venv/bin/python

.PHONY: setup quickstart test unit bench clean

setup:
	bash scripts/setup.sh

quickstart:
	bash scripts/quickstart.sh

# Every test, slow end-to-end ones included.
test:
	$(PY) -m pytest

unit:
	$(PY) -m pytest tests/unit

bench:
	$(PY) bench/startup.py
	$(PY) bench/render_fleet.py

clean:
	rm -rf .ccrp .pytest_cache
