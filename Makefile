# `make demo`: set up, simulate 1200 frames of the city drive (cached), run
# improved_floam_loop on it and print odometry only vs loop closed (APE, % improvement);
# the report with the trajectories, the loop edges and the map is runs/demo/report.html.
# `make test`: set up and run the test suite (pytest-xdist, one worker per core).
.PHONY: setup demo test lint bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	@.venv/bin/slam demo --out runs/demo

test: setup
	@.venv/bin/python -m pytest -q -n auto

lint: setup
	.venv/bin/ruff check . && .venv/bin/ruff format --check .

bench: setup
	for b in benchmarks/bench_*.py; do .venv/bin/python $$b || exit 1; done

clean:
	rm -rf runs .pytest_cache
