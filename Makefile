# Two commands do all the set-up on a fresh machine: `make demo` and `make test`.
PY      ?= python3
VENV    := .venv
VPY     := $(VENV)/bin/python
STAMP   := $(VENV)/.installed
# DDS stays on this host in everything the Makefile starts. A domain id of 20..99 (plus a test worker's
# number): above 101 a domain's DDS ports fall among Linux's ephemeral ports (ROS 2: 0..101 on Linux).
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export ROS_DOMAIN_ID ?= $(shell $(PY) -c "import os; print(os.getpid() % 80 + 20)")
# Python keeps its compiled modules (__pycache__, ignored by git), whatever the caller's environment says: the suite
# starts many `cstomo`, node and board processes, and without them each compiled the package anew (0.3-0.5 s of CPU).
unexport PYTHONDONTWRITEBYTECODE
# BLAS threads fight over 2 cores on the small products of this project: one thread is faster.
export OPENBLAS_NUM_THREADS ?= 1

.PHONY: test test-fast demo venv bench clean

venv: $(STAMP)

# Rebuilt whenever the dependency lists change (a stale .venv is never used). -qq: setuptools' editable
# build prints a boxed warning on every install, which pip shows even with -q; errors (a failed build's
# output included) still show. setuptools' default editable mode: `editable_mode=compat` is deprecated
# (to be removed from setuptools), and the demo, the tests and the colcon install need none of it.
# A .venv without pip is made anew: `python3 -m venv` leaves one when it fails half-way (Debian and
# Ubuntu without the python3-venv package), and pip would then be missing on every later run.
$(STAMP): setup.py requirements-ros.txt
	@echo "setting up $(VENV): the package, its dependencies and rclpy's wheels (once, or when setup.py or"
	@echo "requirements-ros.txt change; 2-6 minutes)"
	@$(VPY) -m pip --version >/dev/null 2>&1 || $(PY) -m venv --clear $(VENV)
	@tick=; if [ -t 1 ]; then (t=0; while sleep 5; do t=$$((t + 5)); printf '\r  pip install: %s s' $$t; done) & \
	    tick=$$!; fi; \
	  $(VPY) -m pip install -q --upgrade pip && \
	  $(VPY) -m pip install -qq -e '.[full,test]' -r requirements-ros.txt; rc=$$?; \
	  if [ -n "$$tick" ]; then kill $$tick; printf '\n'; fi; exit $$rc
	@touch $(STAMP)
	@echo "$(VENV) ready; its commands: . $(VENV)/bin/activate (then cstomo --help)"

# Two workers (pytest-xdist): the 2 cores the suite is sized for. A test file stays on one worker (its
# module fixtures are built once), the longest files first (test/conftest.py LONGEST_FIRST), each worker
# in a ROS domain of its own (test/conftest.py). TEST_JOBS=0 runs it in this one process.
TEST_JOBS ?= 2
XDIST   = -n $(TEST_JOBS) --dist loadfile --no-loadscope-reorder

# Then the tests marked alone (setup.cfg: they judge a board's real time) run by themselves.
test: $(STAMP)
	$(VPY) -m pytest -q $(XDIST) --durations=15 -m "not alone" test; a=$$?; \
	  $(VPY) -m pytest -q --durations=5 -m alone test; b=$$?; [ $$a = 0 ] && [ $$b = 0 ]

# the fast tier: every test not marked slow (setup.cfg); it starts no process and no ROS node
# (test/conftest.py fails a test of it that does) and runs in about a minute
test-fast: $(STAMP)
	$(VPY) -m pytest -q $(XDIST) --durations=10 -m "not slow" test

demo: $(STAMP)
	$(VENV)/bin/cstomo demo

bench: $(STAMP)
	$(VENV)/bin/cstomo bench --quick --out out/bench

clean:
	rm -rf $(VENV) build *.egg-info
