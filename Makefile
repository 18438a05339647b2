# The two set-up commands of the README. Both install into .venv/ first (cached).
.PHONY: install install-fleet demo test test-fast bench

install:
	./scripts/install.sh

# moisst-fleet's Ray (pyproject.toml's `fleet` extra) too; the tests need it
install-fleet:
	MOISST_EXTRAS=fleet ./scripts/install.sh

# Built-in demo: synthetic rig with perturbed priors -> calibration -> before/after error table.
demo: install
	.venv/bin/moisst-synth demo/rig --perturb paper --overwrite
	@# exit status 3 = finished, but some sensor is not converged (its last lines say which to trust): not a failed demo
	.venv/bin/moisst-calibrate demo/rig --output-dir demo/calibration --method moisst-lite || [ $$? -eq 3 ]

# two processes, each taking whole test files (a file's fixtures are built once): much of a stage is one-threaded
test: install-fleet
	.venv/bin/python -m pytest -q -n 2 --dist loadfile tests

test-fast: install-fleet
	.venv/bin/python -m pytest -q -n 2 --dist loadfile -m "not slow" tests

bench: install
	.venv/bin/moisst-bench --quick --out outputs/bench
