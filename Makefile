# Entry points. `make test` is what CI runs (.ci/run) and what the README tells users.
SHELL := /bin/bash
ENV := source ./env.sh

.PHONY: setup test lint bench bench-deps run run-franka teach clean

setup:  ## create .venv, install pinned packages, build ros2_ws, write env.sh (idempotent)
	@scripts/setup.sh

lint: setup  ## ruff over the whole tree
	@$(ENV) && ruff check .

test: setup  ## set up if needed, then lint and the full test suite (two workers, then the timing tests alone; a recap of failures last)
	@$(ENV) && scripts/test.sh

bench: setup bench-deps  ## speed benchmarks; JSON results in bench/results/
	@$(ENV) && python bench/run_all.py

# Bench-only packages (stable-baselines3, the outside PPO reference): installed here, never by setup/test.
# Skipped when the stamp matches the pins; if pip fails, the bench still runs and reports SB3 as skipped.
BENCH_STAMP := .venv/.bench-requirements.sha256
bench-deps: setup
	@want=$$(cat requirements/bench.txt requirements/constraints.txt | sha256sum | cut -d' ' -f1); \
	if [ "$$(cat $(BENCH_STAMP) 2>/dev/null)" != "$$want" ]; then \
	  echo "[bench] installing requirements/bench.txt"; \
	  $(ENV) && python -m pip install -q --disable-pip-version-check -r requirements/bench.txt \
	    -c requirements/constraints.txt 2>&1 | grep -v "is ignored: it is neither a file nor a directory"; \
	  python -c 'import stable_baselines3' && echo "$$want" > $(BENCH_STAMP) \
	    || echo "[bench] warning: stable-baselines3 not installed; its comparison will be skipped"; \
	fi

run: setup  ## the whole stack learning the gear from a failing prior in simulation (composed, lockstep, 30 iterations, ~5 min); ARGS="--iterations 10" etc.
	@$(ENV) && python -m nf_bringup.stack $(ARGS)

run-franka: setup  ## learning on the robot path: franky-sim's FR3 with the gear cell behind libfranka (15 iterations, ~28 min); ARGS="--robot <FCI address> --goal X Y Z" for a real arm
	@$(ENV) && python -m nf_bringup.robot_run $(ARGS)

teach: setup  ## record demonstrations as a bag by teleoperation through the stable law (gear_clamp, a scripted operator, ~2 min); ARGS="--operator keyboard" for you, "--robot franky" to hand-guide franky-sim's FR3
	@$(ENV) && python -m nf_bringup.teach $(ARGS)

clean:  ## remove build products (keeps .venv)
	rm -rf ros2_ws/build ros2_ws/install ros2_ws/log ros2_ws/.build.sha256 env.sh
