# Two entry points for a fresh machine with only python3: `make train` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# `make train` runs the default training (configs/point_mass_a2c_default.yaml, 2e7 steps, ~2 min on the C iteration;
# docs/point_mass.md): a policy that passes the literal Fig. 5 regions and beats the fixed-weight baselines in closed
# loop. The paper's Table IV settings, other configs and lengths (STEPS empty = the config's a2c.total_steps):
#   make train TRAIN_CONFIG=configs/point_mass_a2c.yaml STEPS=1000000 OUT=runs/paper
TRAIN_CONFIG ?= configs/point_mass_a2c_default.yaml
STEPS ?=
OUT ?= runs/point_mass_default

.PHONY: install train test test-slow bench clean policy peg fig7

NATIVE := setup.py a3cqp_rl/native_sources.py $(wildcard a3cqp_rl/*/native/*.c algorithms/native/*.c envs/native/*.c envs/native/*.h)

# (re)installs when the dependencies or a C source change: pip builds the C libraries in place
$(STAMP): pyproject.toml constraints.txt $(NATIVE)
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -c constraints.txt -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# a second `make train` continues (here: just reports) the run in $(OUT) instead of refusing to overwrite it
train: $(STAMP)
	$(BIN)/a3cqp train --config $(TRAIN_CONFIG) $(if $(STEPS),--steps $(STEPS)) --out $(OUT) $(if $(wildcard $(OUT)/checkpoint.pt),--resume)

test: $(STAMP)
	@# pytest exit 5 (no tests collected) is success only while tests/ has no test files.
	$(BIN)/python -m pytest -q; rc=$$?; \
	if [ $$rc -eq 5 ] && ! ls tests/test_*.py >/dev/null 2>&1; then echo "no tests yet"; exit 0; fi; exit $$rc

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

bench: $(STAMP)
	$(BIN)/pip install -q -c constraints.txt -e '.[bench]'
	$(BIN)/a3cqp bench all

# --- The Panda (docs/panda.md). `make peg` evaluates the default learned policy on peg-in-hole against the four
# scripted baselines on 26 trials and prints Table VI. The policy is the one configs/panda_*.yaml name (panda.policy):
# policies/point_mass_fig5_fd_1e6_seed0.pt, the point-mass policy of configs/point_mass_a2c_fig5_fd_1e6.yaml (seed 0),
# shipped so that every machine evaluates the parameters of the README's tables (tests/test_shipped_policy.py trains
# the config and checks it gives that file's parameters bit for bit).
#   make peg PEG_SEED=3                                  other trials
#   make peg PEG_SEEDS=0,3-10 PEG_ARGS="--controllers learned,ik_fc"   several seeds' trials pooled (paired times);
#                  each seed kept in runs/peg_cache as it ends, so the same command resumes a stopped sweep
#   make peg PEG_ARGS="--controllers learned,ik_fc"      a subset of the controllers
#   make peg PEG_ARGS="--set panda.ik_rules_scripted=true"   like for like: the baselines' IK reference follows the
#                  learned arms' tool-axis rules too (the report's line above the table says whose follows which)
#   make fig7      Fig. 7: three insertions with the operator, learned and IK + FC, plotted into runs/peg_fig7
#                  (add the snapshots with: a3cqp plot episode runs/peg_fig7 --strip, needs EGL or OSMesa)
#   make policy    trains that policy here into runs/pm_default (~1 min: 4 s training, then its four candidates on
#                  the Panda, a2c.select_policy: panda) and compares it with the shipped file
PANDA_POLICY := policies/point_mass_fig5_fd_1e6_seed0.pt
PEG_SEED ?= 0
PEG_SEEDS ?=
PEG_ARGS ?=
A3CQP := $(BIN)/a3cqp

# order-only prerequisites: an edited config or a reinstall does not retrain a finished run
runs/pm_default/policy.pt: | $(STAMP) configs/point_mass_a2c_fig5_fd_1e6.yaml
	$(A3CQP) train --config configs/point_mass_a2c_fig5_fd_1e6.yaml --out $(@D) --no-plots $(if $(wildcard $(@D)/checkpoint.pt),--resume)

policy: runs/pm_default/policy.pt
	$(BIN)/python -m algorithms.policy runs/pm_default/policy.pt $(PANDA_POLICY)

peg: | $(STAMP)
	$(A3CQP) evaluate --scene peg_in_hole --trials 26 $(if $(PEG_SEEDS),--seeds $(PEG_SEEDS) --cache runs/peg_cache --out runs/peg26_seeds$(PEG_SEEDS),--seed $(PEG_SEED) --out runs/peg26_seed$(PEG_SEED)) $(PEG_ARGS)

fig7: | $(STAMP)
	$(A3CQP) evaluate --scene peg_in_hole --trials 1 --cycles 3 --controllers learned,ik_fc --out runs/peg_fig7
	$(A3CQP) plot episode runs/peg_fig7
	$(A3CQP) plot episode runs/peg_fig7 --controller ik_fc

clean:
	rm -rf $(VENV) runs .pytest_cache
