# The two commands a fresh clone needs: `make demo` and `make test`.
# Each runs the set-up first; the set-up is a no-op once it has succeeded.
.PHONY: setup demo test bench clean

setup:
	@bash tools/setup.sh

demo: setup
	@.venv/bin/controlled-islanding demo

test: setup
	@bash tools/test.sh

bench: setup
	@.venv/bin/controlled-islanding bench

clean:
	rm -rf .venv build results
