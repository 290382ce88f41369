# Every target that runs code depends on .venv, so each works on a fresh clone.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
TORCH_VERSION ?= 2.13.0

.PHONY: install test test-fast test-deploy netns-tools slurm-tools systemd-tools quick cluster bench bench-time bench-gpu reproduce docs lint clean

# `make reproduce -- --dry-run --seeds 2 main`: the words after `reproduce` are higher-reproduce's
# arguments (write `--seeds 2`, not `--seeds=2`: make takes NAME=VALUE words as its own variables).
# They become targets of make too, so they get an empty rule here. ARGS="..." works as well.
ifeq (reproduce,$(firstword $(MAKECMDGOALS)))
# A word with `=` is a make variable, not an argument: refuse it rather than drop it silently.
SWALLOWED := $(filter-out ARGS=% PY=% TORCH_VERSION=%,$(MAKEOVERRIDES))
ifneq ($(strip $(SWALLOWED)),)
$(error make took '$(SWALLOWED)' as its own variable, not an argument of higher-reproduce: write it with a space (--seeds 2) or pass ARGS="--seeds=2")
endif
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

test: install netns-tools
	$(BIN)/python -m pytest tests

# The multi-host test builds hosts as network namespaces with iproute2's `ip netns` (as root). Install
# it where it is missing and apt-get is there; otherwise that test skips and says why.
netns-tools:
	@command -v ip >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && \
	  apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends iproute2; } || \
	  echo "iproute2 is not installed: the multi-host test will skip"

# deploy/slurm/higher.sbatch on a real Slurm (slurmctld + two slurmd in network namespaces, started by
# the test) and deploy/systemd under a real systemd (PID 1 of namespaces the test makes). Needs root;
# installs Debian's slurm-wlm, munge and systemd where they are missing.
test-deploy: install netns-tools slurm-tools systemd-tools
	$(BIN)/python -m pytest tests/deploy -v

slurm-tools:
	@command -v slurmctld >/dev/null 2>&1 && command -v munged >/dev/null 2>&1 || { \
	  apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
	    slurm-wlm munge; }

systemd-tools:
	@test -x /lib/systemd/systemd && command -v systemd-analyze >/dev/null 2>&1 || { \
	  apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends systemd; }

test-fast: install
	$(BIN)/python -m pytest tests/unit

# A first run: DQN+HER on the small world, 20k frames, about a minute on 2 cores (62 s measured).
quick: install
	$(BIN)/higher-cluster --preset her --world small --frames 20000 $(ARGS)

# 5M frames: 60-80 minutes on the 2-core machine of docs/benchmarks.md (1,088-1,464 frames/s).
cluster: install
	$(BIN)/higher-cluster --preset higher --world paper $(ARGS)

# The paper's profile, 5 seeds x 5M frames: about 32 hours on 2 cores (`make reproduce -- --dry-run`).
reproduce: install
	$(BIN)/higher-reproduce $(REPRODUCE_ARGS) $(ARGS)

bench: install
	mkdir -p results
	$(BIN)/higher-bench all --results results

# The Done-when figures of time to result: her to 40% and 60%, higher to 40%, two seeds each (about an hour).
bench-time: install
	mkdir -p results
	$(BIN)/higher-bench time-to-success --preset her --targets 0.4 0.6 --seeds 0 1 $(ARGS) | tee results/time-to-success-her.txt
	$(BIN)/higher-bench time-to-success --preset higher --targets 0.4 --seeds 0 1 $(ARGS) | tee results/time-to-success-higher.txt

# On a GPU host: the learner on the device and the cluster around it, in under 5 minutes, as JSON.
bench-gpu: install
	mkdir -p results
	$(BIN)/higher-bench gpu $(ARGS) | tee results/gpu.txt

# docs/configuration.md and docs/metrics.md, from config.py and metrics.py (a unit test fails when they drift).
docs: install
	$(BIN)/python -m higher_dist.docs_gen
	$(BIN)/python -m higher_dist.reproduce.results_blocks

lint: install
	$(BIN)/python -m compileall -q higher_dist tests

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis
