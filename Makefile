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

test: install-fleet
	.venv/bin/python -m pytest -q tests

test-fast: install-fleet
	.venv/bin/python -m pytest -q -m "not slow" tests

bench: install
	.venv/bin/moisst-bench --quick --out outputs/bench
