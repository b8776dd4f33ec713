# softshape_ros: `make demo` runs the whole pipeline on the simulated rig, `make test` the tests,
# `make bench` the benchmarks (JSON on stdout). All of them set up .venv and the colcon install first;
# on a ready machine the set-up costs seconds.
SHELL := /bin/bash
.DEFAULT_GOAL := help

PYTHON ?= python3
VENV := .venv
VPY := $(VENV)/bin/python

# DDS discovery stays on this machine, and each make run gets its own domain so parallel
# runs do not cross-talk. A real rig overrides both (e.g. ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET).
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export ROS_DOMAIN_ID ?= $(shell echo $$(( $$$$ % 100 + 101 )))
# The ROS wheels do not set up an ament index; the colcon install provides ours.
export AMENT_PREFIX_PATH := $(CURDIR)/install$(if $(AMENT_PREFIX_PATH),:$(AMENT_PREFIX_PATH))
export PYTHONUNBUFFERED := 1

SOURCES := $(shell find softshape_ros config launch resource -type f -not -path '*/__pycache__/*' 2>/dev/null)
ARGS ?=

.PHONY: help setup venv build demo test bench pretrain clean

help:
	@echo "make demo   - set up, then run the whole pipeline on the simulated rig (see README)"
	@echo "make test   - set up, then run the test suite"
	@echo "make bench  - set up, then run the benchmarks (JSON on stdout)"
	@echo "make pretrain - rebuild a checkpoint on simulation: ARGS=\"--arch tube --as-shipped\" the demo's models/tube_stereo_gray as shipped (two trainings averaged; ARGS=\"--arch tube\": one of them), ARGS=\"--sparse-share 0\" models/ours_stereo_gray"
	@echo "make clean  - remove build products (keeps .venv)"

setup: build

venv: $(VENV)/.stamp

# Idempotent: re-running pip against satisfied pins is fast; the stamp skips it entirely.
# setup.py makes every node file an entry point, so a new node needs the editable install
# redone (its console-script metadata), hence the node files here.
$(VENV)/.stamp: requirements.txt setup.py $(wildcard softshape_ros/nodes/*.py)
	@test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	@touch $(VENV)/COLCON_IGNORE
	set -o pipefail; $(VPY) -m pip install --disable-pip-version-check -q -r requirements.txt 2>&1 \
		| { grep -v 'is ignored: it is neither a file nor a directory' || true; }
	$(VPY) -m pip install --disable-pip-version-check -q --no-deps --no-build-isolation -e .
	@touch $@

build: install/.stamp

# colcon builds the ament_python package exactly as a ROS 2 Jazzy user's `colcon build` does;
# executables land in install/lib/softshape_ros/, where `ros2 run` looks.
# The simulator's numba kernels are compiled once here into their on-disk cache (~30 s of
# CPU on a fresh checkout, ~1 s when nothing changed), not in the first test or worker.
install/.stamp: $(VENV)/.stamp setup.py setup.cfg package.xml $(SOURCES)
	$(VENV)/bin/colcon --log-base log build --merge-install --base-paths . \
		--build-base build --install-base install --event-handlers console_direct-
	$(VPY) -m softshape_ros.sim.warmup
	@touch $@

# The whole pipeline on the simulated rig; a second run reuses finished stages.
# Scale it with ARGS, e.g. make demo ARGS="--scenes 20 --actuations 50" (see softshape demo -h).
demo: build
	$(VENV)/bin/softshape demo --out demo_out $(ARGS)

test: build
	$(VPY) -m pytest test $(ARGS)

bench: build
	$(VPY) -m benchmarks $(ARGS)

# Pre-trained checkpoints (docs/model.md), as shipped: ARGS="--arch tube --as-shipped" models/tube_stereo_gray
# (the demo's), ARGS="--sparse-share 0" models/ours_stereo_gray (its data predates the sparse share).
pretrain: build
	$(VENV)/bin/softshape pretrain $(ARGS)

clean:
	rm -rf build install log .pytest_cache
