# The two commands of the quick start are `make demo` and `make test`; both create .venv
# at the repo root when it is missing and install posecorr into it (editable), which
# builds the C runtime.
PYTHON ?= python3
VENV   := .venv
VPY    := $(VENV)/bin/python
STAMP  := $(VENV)/.posecorr-installed
NATIVE_SOURCES := $(wildcard runtime_c/*.c runtime_c/*.h runtime_c/CMakeLists.txt runtime_c/cmake/* runtime_c/tools/*.c) export/operators.txt
# The install builds the C runtime into the package: where it is gone (`make clean`, `git
# clean`), the install runs again, whatever the stamp's age.
NATIVE_LIBRARY := $(wildcard python/posecorr/_native/libposecorr.*)

.PHONY: install demo test docs bench models programs fuzz embedded clean reinstall

$(STAMP): pyproject.toml setup.py $(NATIVE_SOURCES) $(if $(NATIVE_LIBRARY),,reinstall)
	@test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	$(VPY) -m pip install -q --disable-pip-version-check -e '.[train,test,ros2,embedded,docs,ray]'
	@touch $(STAMP)

reinstall:

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/posecorr demo

# The test files run in parallel (pytest-xdist), one file to a process so that a file's
# shared fixtures (the session corpus, the C builds) are made once; at most TEST_PROCESSES
# processes, fewer on a machine with fewer cores.
TEST_PROCESSES ?= 2
test: $(STAMP)
	$(VPY) -m pytest -q -n auto --maxprocesses $(TEST_PROCESSES) --dist loadfile

# The documentation site (mkdocs.yml, docs/) into site/; its command-line reference, API
# reference and figures are generated at build time (tools/docs_site.py).
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VPY) -m mkdocs build --strict

# bench/ and tools/ are harnesses of the checkout (run from the repo root), not in the wheel.
# The LM comparison package is installed for the benchmark only, without its dependencies:
# its torch requirement would pull CUDA builds, and it runs on the torch already here.
bench: $(STAMP)
	$(VPY) -m pip install -q --disable-pip-version-check --no-deps torch-levenberg-marquardt
	$(VPY) -m bench
	$(VPY) bench/ros2_latency.py

models: $(STAMP)
	$(VPY) -m tools.models
	@$(MAKE) --no-print-directory programs

# The shipped models' one-pose programs compiled to C (runtime_c/programs_compiled.c): the
# loader runs these in place of its interpreter where a program's shape matches.
# Besides the shipped models: the demo's physics + PMC model, refitted (its shapes do not
# depend on the fitted values).
programs: $(STAMP)
	@cmake -S runtime_c -B build/shapes -DCMAKE_BUILD_TYPE=Release >/dev/null
	@cmake --build build/shapes --target posecorr-print-shapes --parallel 2 >/dev/null
	$(VPY) -m tools.models --demo-physics-pmc build/shapes/physics-pmc.onnx
	$(VPY) runtime_c/tools/compile_programs.py --shapes build/shapes/posecorr-print-shapes models/*.onnx \
	    build/shapes/physics-pmc.onnx

fuzz:
	$(MAKE) -C runtime_c -f fuzz.mk

# Cross-builds the runtime for a Cortex-M4F, runs the firmware in QEMU and compares with x86
# (needs gcc-arm-none-eabi, libnewlib-arm-none-eabi, qemu-system-arm; see runtime_c/embedded).
# The networks table goes to bench/results, where docs/guides/microcontrollers.md reads it.
embedded: $(STAMP)
	@$(MAKE) --no-print-directory -C runtime_c/embedded PYTHON="$(abspath $(VPY))" \
	    NETWORKS_JSON="$(abspath bench/results/embedded_networks.json)"

clean:
	rm -rf build site runtime_c/build* python/posecorr/_native *.egg-info
