# Every target bootstraps .venv on a fresh machine (python3, pip and the package index only).
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test check bench fuzz fuzz-cli clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	@# the ros extra (ROS 2 Jazzy wheels) exists for some Pythons only: fall back without it
	@echo "installing tpsr-ros with its test, dds, dask and ros (ROS 2 Jazzy wheels) extras into $(VENV)"
	@$(PY) -m pip install --quiet -e '.[test,dds,dask,ros]' 2> $(VENV)/ros-extra.log \
	|| { echo "note: no ROS 2 Jazzy wheels for $$($(PY) -V); installing without rclpy (Cyclone DDS backend; pip's reason in $(VENV)/ros-extra.log)"; \
	     $(PY) -m pip install --quiet -e '.[test,dds,dask]'; }
	@# colcon must not take the venv's ROS packages (share/*/package.xml) for the workspace's
	touch $(VENV)/COLCON_IGNORE
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m learner.demo

# Python caches compiled modules even where the environment says not to: the suite starts
# about 160 Python processes (test workers, nodes, commands) that would otherwise each compile
# the project's modules again, and each worker would rewrite every test module's asserts
unexport PYTHONDONTWRITEBYTECODE

# the whole suite in parallel (pytest-xdist): one worker per core and one more; idle workers
# steal queued tests; tests/conftest.py pins BLAS to one thread per worker. Many tests wait
# (on node processes, discovery, real-time replays) and the extra worker runs another in
# that time: on two cores the suite took 273 s with two workers (420 s of CPU, the cores a
# quarter idle), 199-224 s with three and 213 s with four, for the same CPU time
WORKERS ?= $(shell $(PYTHON) -c "import os; print((os.cpu_count() or 1) + 1)")
test: $(STAMP)
	$(PY) -m pytest -q -n $(WORKERS) --dist worksteal

# the fast tier while working: every test not marked slow
check: $(STAMP)
	$(PY) -m pytest -q -n auto -m "not slow"

bench: $(STAMP)
	$(PY) -m benchmarks

# longer mutation fuzzing of every file format we read; rerun a failure with its FUZZ_SEED
fuzz: $(STAMP)
	@seed=$${FUZZ_SEED:-$$(date +%s)}; echo "FUZZ_SEED=$$seed"; \
	FUZZ_SEED=$$seed FUZZ_CASES=$${FUZZ_CASES:-2000} RECOVER_ALL=1 $(PY) -m pytest -q \
	  tests/test_fuzz.py tests/test_recover_conformance.py

# mutated inputs through the real commands and nodes, each under a 2 GiB address-space cap
# and a 20 s limit; rerun one case with --seed S --case N
fuzz-cli: $(STAMP)
	nice -n 10 $(PY) tests/fuzz_cli.py --minutes $${FUZZ_MINUTES:-15} \
	  $${FUZZ_SEED:+--seed $$FUZZ_SEED} --out fuzz_output

clean:
	rm -rf $(VENV) demo_output fuzz_output
