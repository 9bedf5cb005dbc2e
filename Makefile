# HAUWM: `make demo` and `make test` install into .venv first when needed.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO := demo-out
# Headless MuJoCo rendering on a CPU box (docs/environments.md); a user's own setting wins.
export MUJOCO_GL ?= osmesa
export PYOPENGL_PLATFORM ?= osmesa
# Debian packages the project needs: OSMesa for headless MuJoCo rendering.
APT_PACKAGES := libosmesa6 libgl1 libegl1

.PHONY: install demo test test-all test-floor bench bench-checks clean system-deps disk-check

install: $(STAMP)

# constraints.txt: the exact versions CI tests (pyproject.toml has ranges; see the README on GPU machines)
$(STAMP): pyproject.toml constraints.txt
	@$(MAKE) --no-print-directory system-deps
	@$(MAKE) --no-print-directory disk-check
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]" -c constraints.txt
	touch $(STAMP)

# torch 2.14.1 with its CUDA libraries makes .venv about 6.3 GB: say so before pip fails half-way with ENOSPC.
INSTALL_MIN_FREE_GB ?= 7
disk-check:
	@if ! ls -d $(VENV)/lib/python*/site-packages/torch >/dev/null 2>&1; then \
	  free_gb=$$(( $$(df -Pk . | awk 'NR==2 {print $$4}') / 1048576 )); \
	  if [ "$$free_gb" -lt "$(INSTALL_MIN_FREE_GB)" ]; then \
	    echo "make install: $(VENV) needs about $(INSTALL_MIN_FREE_GB) GB of disk (torch with its CUDA libraries)," \
	         "and the filesystem of $(CURDIR) has $$free_gb GB free: free some space (df -h .)," \
	         "or run 'make install INSTALL_MIN_FREE_GB=0' to try anyway" >&2; \
	    exit 1; \
	  fi; \
	fi

system-deps:
	@missing=$$(for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing Debian packages: $$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	  else \
	    echo "warning: missing Debian packages ($$missing); MuJoCo rendering needs them: sudo apt-get install $$missing"; \
	  fi; \
	fi

demo: install
	rm -rf $(DEMO)
	$(BIN)/hauwm shards sample-data --out $(DEMO)/ssv2 --clips 96 --with-broken
	$(BIN)/hauwm shards build --annotations $(DEMO)/ssv2/annotations --videos $(DEMO)/ssv2/videos \
	    --split train --split validation --out $(DEMO)/shards --clips-per-shard 16 --workers 2 --max-error-rate 0.2
	$(BIN)/hauwm shards inspect $(DEMO)/shards --verify
	$(BIN)/hauwm shards preview $(DEMO)/shards --out $(DEMO)/preview.png
	$(BIN)/hauwm pretrain fit --config configs/pretrain/tiny.yaml --data.shards $(DEMO)/shards \
	    --trainer.default_root_dir $(DEMO)/pretrain
	$(BIN)/hauwm pretrain export $(DEMO)/pretrain/checkpoints/last.ckpt --out $(DEMO)/export
	$(BIN)/hauwm pretrain analyze --model $(DEMO)/export --shards $(DEMO)/shards --out $(DEMO)/analysis
	$(BIN)/hauwm finetune --config configs/finetune/demo.yaml --pretrained $(DEMO)/export --logdir $(DEMO)/finetune
	@echo
	@echo "demo done:"
	@echo "  shards        $(DEMO)/shards        (preview: $(DEMO)/preview.png)"
	@echo "  pre-training  $(DEMO)/pretrain      (TensorBoard: .venv/bin/tensorboard --logdir $(DEMO)/pretrain)"
	@echo "  export        $(DEMO)/export"
	@echo "  analysis      $(DEMO)/analysis      (disagreement vs k and imagined rollouts, PNG + figures.json)"
	@echo "  fine-tuning   $(DEMO)/finetune"

test: install
	$(BIN)/python -m pytest

test-all: install
	$(BIN)/python -m pytest -m "slow or not slow"

# Every test on the oldest torch pyproject.toml admits (torch 2.11: the GPU machines' image), in
# .venv-floor; constraints.txt's other versions, less those that pin torch's own (triton, CUDA, setuptools < 82).
# Downloads about 3 GB of torch 2.11 CUDA wheels from PyPI the first time (1.5 minutes here); then 13–21 minutes of tests on 2 cores.
FLOOR := .venv-floor
test-floor:
	@$(MAKE) --no-print-directory system-deps
	test -x $(FLOOR)/bin/python || $(PYTHON) -m venv $(FLOOR)
	grep -v -E '^(torch|triton|nvidia-.*|cuda-.*|setuptools)==' constraints.txt > $(FLOOR)/constraints.txt
	$(FLOOR)/bin/python -m pip install --quiet --upgrade pip
	$(FLOOR)/bin/python -m pip install --quiet torch==2.11.0 -e ".[test]" -c $(FLOOR)/constraints.txt
	$(FLOOR)/bin/python -m pytest -m "slow or not slow"

# speed figures (minutes); the paper-claim, learning and world-model action checks take ~3, ~25 and ~10 minutes: `make bench-checks`
BENCH_SPEED := bench/bench_shards.py bench/bench_loader.py bench/bench_pretrain.py bench/bench_envs.py bench/bench_agent.py bench/bench_datasets.py
BENCH_CHECKS := bench/bench_pretrain_claim.py bench/bench_learning.py bench/bench_model_actions.py

bench: install
	@for script in $(BENCH_SPEED); do echo "== $$script"; $(BIN)/python $$script || exit 1; done

bench-checks: install
	@for script in $(BENCH_CHECKS); do echo "== $$script"; $(BIN)/python $$script || exit 1; done

clean:
	rm -rf $(DEMO) runs .pytest_cache
