# pcrelight — set-up-and-go targets. `make demo` runs the pipeline on the shipped sample,
# `make test` runs the tests; both set everything up first (venv, and apt packages when root).
SHELL := /bin/bash
VENV  := .venv
PY    := $(VENV)/bin/python
PCR   := $(VENV)/bin/pcrelight
STAMP := $(VENV)/.installed
SAMPLE := data_samples
OUT   := out/demo
CFG   := configs/demo.toml
# Debian packages: Open3D needs libusb; headless GL needs Mesa's EGL/GL; Mitsuba's LLVM backend
# needs LLVM 19 (Debian 12's LLVM 15 aborts); OSMesa for the documented fallback; Chromium: tests/test_report.py
# opens the run report in it (headless).
APT_PKGS := libusb-1.0-0 libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 libllvm19 libosmesa6 chromium

.PHONY: setup apt demo demo-own test bench evaluate trade data pano clean help
.DEFAULT_GOAL := help

help:
	@echo "make demo   - run the whole pipeline on the shipped sample (ends with $(OUT)/relit.png and $(OUT)/report.html)"
	@echo "make demo-own - the one command on a user-style capture (data_samples/own/: cm, Z-up scan, .hdr, .glb) → out/demo-own/composite.png"
	@echo "make test   - run the test suite"
	@echo "make bench  - bench/manifest.toml's quick subset into bench/_work/quick/ (~10 min); FULL=1: every run, its CSV/PNG under bench/<topic>/ (hours)"
	@echo "make evaluate - Table 2 on the shipped scene: out/eval/table.{json,md}"
	@echo "make trade  - the speed/accuracy sweep on the shipped scene; rewrites configs/presets/ (~30 min; resumes)"
	@echo "make data   - rebuild data_samples/ (the small ground truth, byte-identical for seed 0; ~3.5 CPU-hours)"
	@echo "make pano   - only data_samples/pano.exr (the HDR panorama; the bytes make data writes; ~4 CPU-minutes)"
	@echo "make setup  - create $(VENV) and install pcrelight (and apt packages when root); compiles numba's kernels once (~1 min)"
	@echo "make clean  - remove out/ and caches"

apt:
	@missing=$$(for p in $(APT_PKGS); do dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then echo "installing apt packages:" $$missing; \
	    export DEBIAN_FRONTEND=noninteractive; apt-get update -qq && apt-get install -y -qq --no-install-recommends $$missing >/dev/null; \
	  else echo "warning: missing apt packages (run as root or install them):" $$missing; fi; fi

$(STAMP): pyproject.toml
	$(MAKE) --no-print-directory apt
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	$(PY) -m pipeline.run.warm
	touch $@

setup: $(STAMP)

# ------------------------------------------------------------------ the demo: one target per stage output
# Each stage runs only when its inputs changed. A stage that is not built yet (exit 2 and its
# "is not implemented yet" line) stops the chain with a message saying where; the later stages then
# say they were skipped. Any other failure (a bad config value is exit 2 too) stops make with its status.
STOPPED := $(OUT)/.stopped
define stage
	@mkdir -p $(OUT); if [ -e $(STOPPED) ]; then echo "make demo: skipping $(1) (pipeline stopped at $$(cat $(STOPPED)))"; exit 0; fi; \
	echo "+ pcrelight $(1) $(2)"; { $(PCR) $(1) $(2) --config $(CFG) 2>&1 1>&3 | tee $(OUT)/.stage.err 1>&2; rc=$${PIPESTATUS[0]}; } 3>&1; \
	if [ $$rc = 2 ] && [ ! -e $(3) ] && grep -q "is not implemented yet" $(OUT)/.stage.err; then echo "$(1)" > $(STOPPED); echo "make demo: the pipeline stops at '$(1)': not implemented yet"; exit 0; fi; exit $$rc
endef

demo: $(STAMP)
	@rm -f $(STOPPED)
	@$(MAKE) --no-print-directory $(OUT)/relit.png $(OUT)/photo/composite.png
	$(PCR) report $(OUT) --inputs $(SAMPLE) --out $(OUT)/report.html -q
	@if [ -e $(STOPPED) ]; then echo "make demo: ran the pipeline up to '$$(cat $(STOPPED))', which is not implemented yet; outputs in $(OUT)/"; \
	 else echo "make demo: done — $(OUT)/photo/composite.png (the knot in the photo; layers: $(OUT)/photo/composite.exr), $(OUT)/relit.png (HDR: $(OUT)/relit.exr, stats: $(OUT)/stats.json, the run: $(OUT)/report.html)"; fi

$(OUT)/exposure.npz: $(SAMPLE)/photo.exr $(SAMPLE)/cloud_ldr.ply $(CFG)
	$(call stage,expose-match,$(SAMPLE)/photo.exr $(SAMPLE)/cloud_ldr.ply --out $@ --photo-ldr $(OUT)/photo_ldr.exr --preview $(OUT)/expose_match.png,$@)

$(OUT)/cubemaps/cameras.npz: $(SAMPLE)/cloud_ldr.ply $(CFG)
	$(call stage,render-cubemaps,$(SAMPLE)/cloud_ldr.ply --out $(OUT)/cubemaps --preview $(OUT)/cubemaps.png,$@)

$(OUT)/hdr_faces/renderings.npz: $(OUT)/cubemaps/cameras.npz $(OUT)/exposure.npz $(SAMPLE)/photo.exr
	$(call stage,patchmatch,$(OUT)/cubemaps --photo $(SAMPLE)/photo.exr --photo-ldr $(OUT)/photo_ldr.exr --exposure $(OUT)/exposure.npz --out $(OUT)/hdr_faces --preview $(OUT)/hdr_faces.png,$@)

$(OUT)/cloud_proj.ply: $(SAMPLE)/cloud_ldr.ply $(OUT)/hdr_faces/renderings.npz $(OUT)/exposure.npz
	$(call stage,reproject,$(SAMPLE)/cloud_ldr.ply $(OUT)/cubemaps $(OUT)/hdr_faces --photo $(SAMPLE)/photo.exr --exposure $(OUT)/exposure.npz --out $@ --preview $(OUT)/cloud_proj.png,$@)

$(OUT)/cloud_hdr.ply: $(OUT)/cloud_proj.ply
	$(call stage,poisson,$< --ldr $(SAMPLE)/cloud_ldr.ply --out $@ --preview $(OUT)/cloud_hdr.png,$@)

$(OUT)/bsh.npz: $(OUT)/cloud_hdr.ply
	$(call stage,build-bsh,$< --out $@ --preview $(OUT)/bsh.png,$@)

$(OUT)/relit.png: $(OUT)/bsh.npz $(SAMPLE)/scene.json
	$(call stage,relight,--bsh $(OUT)/bsh.npz --object $(SAMPLE)/object.glb --scene $(SAMPLE)/scene.json --view view1 --out $(OUT),$@)

# the knot in the photo: relight from the photo's registered camera (exposure.npz), its shadow on the room
$(OUT)/photo/composite.png: $(OUT)/bsh.npz $(OUT)/exposure.npz $(SAMPLE)/photo.exr
	$(call stage,relight,--bsh $(OUT)/bsh.npz --object $(SAMPLE)/object.glb --scene $(SAMPLE)/scene.json --photo $(SAMPLE)/photo.exr --exposure $(OUT)/exposure.npz --out $(OUT)/photo,$@)

# ------------------------------------------------------------------ tests, benchmarks, evaluation
test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) bench/run.py $(if $(FULL),--full)

evaluate: $(STAMP)
	$(PCR) evaluate --truth $(SAMPLE) --run-all out/eval --config configs/evaluate.toml

# The shipped presets: the sweep's rows (configs/presets/trade.csv; rows already there are not measured again),
# the front (trade.png) and fast/balanced/exact.toml by pipeline/measure/trade.py's rule. TRADE_BUDGET bounds it [min].
TRADE_BUDGET ?= 40
trade: $(STAMP)
	$(PCR) trade --scene $(SAMPLE) --config $(CFG) --out configs/presets --work out/trade/small --budget-min $(TRADE_BUDGET)

data: $(STAMP)
	$(PCR) make-scene --preset small --out $(SAMPLE) --seed 0

# only the HDR panorama of the shipped scene (pano.exr, truth/truth_pano.npz, scene.json's "panorama"): the bytes
# `make data` writes, in minutes instead of hours
pano: $(STAMP)
	$(PCR) make-scene --preset small --out $(SAMPLE) --seed 0 --only panorama

clean:
	rm -rf out .pytest_cache
	find . -name __pycache__ -type d -prune -exec rm -rf {} +
	rm -f $(STAMP)   # the numba kernels' cache went with __pycache__: the next setup compiles it again

# ------------------------------------------------------------------ fuzzing (issue 30): the bounded tests, longer
# Readers: FUZZ_EXAMPLES hypothesis examples a property (random, not the derandomised CI draw); kill -9:
# KILL_TRIALS trials a stage (every stage, make-scene and evaluate included) and KILL_TRIALS/5 SIGTERM/SIGINT
# at random points a stage; then ATHERIS_SECONDS of coverage-guided fuzzing a reader when atheris is
# installed. Figures: out/fuzz/readers.json (inputs tried per reader) and out/fuzz/kill.json.
FUZZ_EXAMPLES ?= 2000
KILL_TRIALS ?= 50
ATHERIS_SECONDS ?= 60
.PHONY: fuzz
fuzz: $(STAMP)
	@mkdir -p out/fuzz; rm -f out/fuzz/readers.json out/fuzz/kill.json
	PCRELIGHT_FUZZ_EXAMPLES=$(FUZZ_EXAMPLES) PCRELIGHT_FUZZ_REPORT=out/fuzz/readers.json $(PY) -m pytest -q -p no:cacheprovider tests/test_fuzz_readers.py
	PCRELIGHT_KILL_TRIALS=$(KILL_TRIALS) PCRELIGHT_KILL_STAGES=all PCRELIGHT_KILL_REPORT=out/fuzz/kill.json $(PY) -m pytest -q -p no:cacheprovider tests/test_kill.py
	@if $(PY) -c "import atheris" 2>/dev/null; then for r in ply exr hdr npz obj gltf glb toml scene; do \
	  echo "+ atheris $$r ($(ATHERIS_SECONDS) s)"; \
	  $(PY) tests/fuzz_atheris.py $$r -max_total_time=$(ATHERIS_SECONDS) -rss_limit_mb=4096 -timeout=30 2>&1 | \
	    grep -E "^Done|Uncaught|crash-|Error:"; test $${PIPESTATUS[0]} = 0 || exit 1; done; \
	else echo "make fuzz: atheris is not installed (pip install atheris): hypothesis only"; fi
	@cat out/fuzz/readers.json out/fuzz/kill.json

# ------------------------------------------------------------------ numerical extremes (issue 28): every case of tests/test_extremes.py
# (the CI subset runs in `make test`); writes docs/extremes.md from the measured rows.
.PHONY: extremes
extremes: $(STAMP)
	PCRELIGHT_EXTREMES=full $(PY) -m pytest -q -p no:cacheprovider -rxs tests/test_extremes.py

# ------------------------------------------------------------------ your object in your room: the one command
# data_samples/own/ holds a capture as users bring it (data_samples/own/convert.py: a 60k-point scan in cm with
# Z up and no normals, the photo as Radiance .hdr, a renamed glTF); the photo carries no EXIF, so its field of
# view is given (--photo-fov). Everything else (import, placement, camera) is decided by `run`; the stages take
# the demo's options ($(CFG): 256² cube faces instead of 1024², PatchMatch, the hybrid gatherer; flags win).
OWN := out/demo-own
demo-own: $(STAMP)
	$(PCR) run $(CFG) --cloud $(SAMPLE)/own/atrium_scan.ply --photo $(SAMPLE)/own/atrium.hdr --object $(SAMPLE)/own/knot.glb \
	    --photo-fov 70 --out $(OWN)
	@echo "make demo-own: done — $(OWN)/composite.png (the object over the room), $(OWN)/relit.png, $(OWN)/run.json (every decision)"
