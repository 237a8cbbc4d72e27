# Two commands do all set-up on a fresh machine: `make run` and `make test`.
# `make test` builds the documentation too (tests/test_docs.py: mkdocs build --strict, examples).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test walkthroughs bench bench-quick lint golden docs clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test,bench,docs]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/fusionlog run pipeline/ajgl2009.toml --force

# The numerical modules once more under other OpenBLAS kernels (tests/other_kernels.py).
NUMERIC := tests/test_retrodict_t2t.py tests/test_exact.py tests/test_exact_per_run.py tests/test_per_run.py \
	tests/test_architectures.py tests/test_numerics.py tests/test_fusion.py \
	tests/test_reference_filterpy.py tests/test_metrics.py tests/test_replay_sources.py \
	tests/test_models.py tests/test_api.py tests/test_nonlinear_core.py \
	tests/test_replay_real_logs.py tests/test_replay_truth.py tests/test_replay_fast.py \
	tests/test_exact_replay.py tests/test_exact_nodes.py \
	tests/test_references_linear.py tests/test_references_exact.py tests/test_references_nonlinear.py \
	tests/test_registry.py tests/test_ici.py tests/test_trajectory.py tests/test_identify.py \
	tests/test_valid_inputs.py tests/test_api_misuse.py tests/test_bound.py tests/test_ei.py \
	tests/test_latency.py tests/test_latency_replay.py tests/test_latency_corr.py \
	tests/test_long_logs.py tests/test_latency_nonlinear.py tests/test_nis_nonlinear.py \
	tests/test_nonlinear_one_run.py \
	tests/test_long_more.py tests/test_long_replay.py tests/test_replay_kernels.py \
	tests/test_long_rest.py tests/test_long_truth_model.py tests/test_long_late_random.py \
	tests/test_long_retrodict.py \
	tests/test_long_late_more.py tests/test_long_late_rules.py tests/test_long_rs.py \
	tests/test_long_late_rs.py

# The goldens and the exactness tests once more with every fast path sent to its plain
# reference path (core/reference.py; benchmarks/README.md "Fast paths").
REFERENCE := tests/test_golden.py tests/test_exact.py tests/test_exact_per_run.py \
	tests/test_exact_nodes.py tests/test_exact_replay.py tests/test_replay_fast.py \
	tests/test_references_exact.py tests/test_replay.py tests/test_mcap_read.py tests/test_mcap_wire.py

test: $(STAMP)
	$(BIN)/pytest
	$(BIN)/python tests/other_kernels.py $(NUMERIC)
	FUSIONLOG_REFERENCE_PATHS=1 $(BIN)/pytest -p no:cacheprovider $(REFERENCE)

# The documentation's walk-throughs on the shared real logs that take minutes (identify on evo's
# bag); `make test` skips them to stay within a few minutes on 2 cores.
walkthroughs: $(STAMP)
	FUSIONLOG_WALKTHROUGHS=1 $(BIN)/pytest -p no:cacheprovider tests/test_identify.py -k walkthrough

bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py

bench-quick: $(STAMP)
	$(BIN)/python benchmarks/run_all.py --quick

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks

golden: $(STAMP)
	FUSIONLOG_UPDATE_GOLDEN=1 $(BIN)/pytest tests/test_golden.py

docs: $(STAMP)
	$(BIN)/mkdocs build --strict

clean:
	rm -rf $(VENV)
