# libFuzzer run of the loader (+ pc_run on whatever loads), with ASan and UBSan.
#   make fuzz                      (from the repo root; FUZZ_SECONDS=600 by default)
#   make -C runtime_c -f fuzz.mk FUZZ_SECONDS=60
# Needs clang (apt-get install clang). Seeds are the test graphs (needs onnx in PYTHON).
FUZZ_SECONDS ?= 600
FUZZ_CC ?= clang
BUILD := ../build/fuzz
SEEDS := $(BUILD)/seeds
CORPUS := $(BUILD)/corpus
PYTHON ?= $(firstword $(wildcard ../.venv/bin/python) python3)

.PHONY: run build seeds clean

run: build seeds
	@mkdir -p $(CORPUS) $(BUILD)/crashes
	$(BUILD)/pc_fuzz_load -max_total_time=$(FUZZ_SECONDS) -timeout=10 -rss_limit_mb=2048 \
	    -max_len=65536 -print_final_stats=1 -artifact_prefix=$(BUILD)/crashes/ \
	    $(CORPUS) $(SEEDS) 2>&1 | tee $(BUILD)/fuzz.log | grep -E "^#[0-9]+.*(pulse|DONE)|ERROR|stat::" ; \
	    status=$${PIPESTATUS[0]}; grep -E "stat::number_of_executed_units|Done [0-9]+ runs" $(BUILD)/fuzz.log; exit $$status
SHELL := /bin/bash

build:
	cmake -S . -B $(BUILD) -DCMAKE_C_COMPILER=$(FUZZ_CC) -DCMAKE_BUILD_TYPE=RelWithDebInfo \
	    -DPC_FUZZ=ON -DPC_BUILD_TESTS=OFF > /dev/null
	cmake --build $(BUILD) --target pc_fuzz_load --parallel 2

seeds:
	@mkdir -p $(SEEDS)
	$(PYTHON) tests/make_seeds.py $(SEEDS)

clean:
	rm -rf $(BUILD)
