# Every target that runs code depends on .venv, so each works on a fresh clone.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
TORCH_VERSION ?= 2.13.0

.PHONY: install test test-fast cluster bench bench-time reproduce lint clean

# `make reproduce -- --dry-run --seeds 2 main`: the words after `reproduce` are higher-reproduce's
# arguments (write `--seeds 2`, not `--seeds=2`: make takes NAME=VALUE words as its own variables).
# They become targets of make too, so they get an empty rule here. ARGS="..." works as well.
ifeq (reproduce,$(firstword $(MAKECMDGOALS)))
REPRODUCE_ARGS := $(wordlist 2,$(words $(MAKECMDGOALS)),$(MAKECMDGOALS))
ifneq ($(REPRODUCE_ARGS),)
$(eval $(REPRODUCE_ARGS):;@:)
endif
endif

install: $(STAMP)

# torch first, at the version that is a local CPU wheel on the dev/CI machines; the package's own
# range admits it, so the editable install adds nothing heavy.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/python -m pip install -q torch==$(TORCH_VERSION)
	$(BIN)/python -m pip install -q -e '.[dev,minigrid,plot,tensorboard]'
	touch $(STAMP)

test: install
	$(BIN)/python -m pytest tests

test-fast: install
	$(BIN)/python -m pytest tests/unit

cluster: install
	$(BIN)/higher-cluster --preset higher --world paper $(ARGS)

reproduce: install
	$(BIN)/higher-reproduce $(REPRODUCE_ARGS) $(ARGS)

bench: install
	mkdir -p results
	$(BIN)/higher-bench all --results results

# Tens of minutes: the real cluster until greedy success reaches the target (not part of `make bench`).
bench-time: install
	mkdir -p results
	$(BIN)/higher-bench time-to-success --preset her --target 0.4 $(ARGS) | tee results/time-to-success-her.txt

lint: install
	$(BIN)/python -m compileall -q higher_dist tests

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis
