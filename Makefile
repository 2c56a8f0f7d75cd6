# Entry points. `make test` is what CI runs (.ci/run) and what the README tells users.
SHELL := /bin/bash
ENV := source ./env.sh

.PHONY: setup test lint bench run clean

setup:  ## create .venv, install pinned packages, build ros2_ws, write env.sh (idempotent)
	@scripts/setup.sh

lint: setup  ## ruff over the whole tree
	@$(ENV) && ruff check .

test: setup  ## set up if needed, then lint and the full test suite
	@$(ENV) && ruff check . && python -m pytest

bench: setup  ## speed benchmarks; JSON results in bench/results/
	@$(ENV) && python bench/run_all.py

run: setup  ## the whole stack learning the gear in simulation (lockstep); ARGS="--iterations 20" etc.
	@$(ENV) && python -m learner_node.stack --config config/gear.yaml $(ARGS)

clean:  ## remove build products (keeps .venv)
	rm -rf ros2_ws/build ros2_ws/install ros2_ws/log ros2_ws/.build.sha256 env.sh
