# swarmrec task runner. CI runs `make test` (see .ci/run); nothing CI does is
# out of a developer's reach.
#
#   make run     the main job: a local swarm of 10 robots (real processes, real zenoh router) on the synthetic world
#   make evaluate  the offline evaluation (no processes): centralized and 10 robots
#   make test    regenerated-code check, lint, types, all tests (unit, local processes, containers, training, the compiled data plane)
#   make dataplane  the compiled data plane (target/release/swarmrec-dataplane; Rust installed by rustup if absent)
#   make landmarks  the cooperative landmark recognition simulation (10 robots, 118 configurations) and its figures
#   make bench   benchmarks, figures written to bench/results/
#   make contracts  regenerate services/ (each service kind's contract) and the architecture figure
#   make images  container engine (installed and started if none answers) and the swarm's images
#   make swarm-up ROBOTS=4   a compose swarm of ROBOTS robots (3 to 10) + Prometheus, on this host
#   make swarm-run           replay the synthetic world through it (report in runs/compose/report)
#   make swarm-down          remove its containers, network and volumes
#   make k8s-up              a real single-node Kubernetes cluster here (as root; built the first time, 8-17 min), the images loaded into it
#   make k8s-apply           the local overlay (3 robots, mutual TLS): its Secrets (swarmrec k8s secrets), then kubectl apply -k
#   make k8s-run             replay the synthetic world through a fresh namespace of the cluster (swarmrec run --deployment k8s)
#   make k8s-down            the cluster off and undone (the built binaries stay cached)
#   make train-env           the model-training environment (.venv-train: PyPI torch, several GB)
#   make train-landmarks     retrain models/landmarks/landmark_cnn.onnx (CPU, about 6 minutes)
#   make train-detector      retrain models/detector/office_detector.onnx
#   make train-descriptor    retrain models/descriptor/descriptor.onnx (place recognition from images)
#
# Every target sets up its own virtual environment first (.venv, pinned by
# requirements.lock), so a fresh clone needs only python3 and make. Training
# has its own (.venv-train, pinned by models/requirements-train.txt):
# PyPI's torch is the multi-GB CUDA build and never enters .venv or an image.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
RUN_OUT ?= runs/swarm
ROBOTS  ?= 4
COMPOSE_OUT ?= runs/compose
K8S_OVERLAY ?= k8s/overlays/local
KUBECTL     := deploy/k8s/kubectl.sh
LANDMARKS_OUT ?= runs/landmarks
TRAIN_VENV  := .venv-train
TRAIN_STAMP := $(TRAIN_VENV)/.installed-stamp
TRAIN_REQS  := models/requirements-train.txt
# The compiled data plane (docs/dataplane.md): crates from crates.io, pinned by the
# committed Cargo.lock. It needs Rust >= 1.85 (zenoh 1.10 and prost 0.14): cargo on PATH or
# rustup's ~/.cargo/bin (this project's machines have it; Debian's rustc 1.63 is too old),
# and a C++17 compiler for numpy's vendored argsort (dataplane/vendor: Debian's g++).
CARGO ?= $(shell command -v cargo 2>/dev/null || echo $(HOME)/.cargo/bin/cargo)
DATAPLANE := target/release/swarmrec-dataplane

.PHONY: help dataplane dataplane-test venv contracts train-env train-landmarks train-detector train-descriptor landmarks run evaluate test unit lint typecheck proto check-proto bench images swarm-up swarm-run swarm-down k8s-up k8s-apply k8s-run k8s-down clean

help:
	@sed -n 's/^#   //p' Makefile

$(STAMP): pyproject.toml requirements.lock
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c requirements.lock -e '.[dev]'
	@touch $(STAMP)

venv: $(STAMP)

# --no-deps for swarmrec itself: training needs only its renderers (numpy, opencv,
# numba, tqdm), which the pinned requirements already hold. --no-cache-dir: torch and
# its CUDA libraries are ~4 GB of wheels that would stay in pip's cache beside the
# ~7 GB installed (a CI run once ran out of disk installing them).
$(TRAIN_STAMP): $(TRAIN_REQS) pyproject.toml
	@test -x $(TRAIN_VENV)/bin/python || $(PYTHON) -m venv $(TRAIN_VENV)
	$(TRAIN_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(TRAIN_VENV)/bin/python -m pip install --quiet --no-cache-dir -r $(TRAIN_REQS)
	$(TRAIN_VENV)/bin/python -m pip install --quiet --no-deps -e .
	@touch $(TRAIN_STAMP)

train-env: $(TRAIN_STAMP)

train-landmarks: $(TRAIN_STAMP)
	$(TRAIN_VENV)/bin/python models/landmarks/train.py

train-detector: $(TRAIN_STAMP)
	$(TRAIN_VENV)/bin/python models/detector/train.py

train-descriptor: $(TRAIN_STAMP)
	$(TRAIN_VENV)/bin/python models/descriptor/train.py

landmarks: $(STAMP)
	$(BIN)/swarmrec landmarks --out $(LANDMARKS_OUT)

run: $(STAMP) $(DATAPLANE)
	$(BIN)/swarmrec run --dataset synthetic --robots 10 --out $(RUN_OUT)

evaluate: $(STAMP)
	$(BIN)/swarmrec evaluate --dataset synthetic --out runs/evaluate

test: $(STAMP) $(TRAIN_STAMP) check-proto lint typecheck dataplane-test
	$(BIN)/python -m pytest

# The compiled data plane's rules are below `test`.

$(CARGO):
	@echo "no cargo found (PATH, ~/.cargo/bin): install Rust >= 1.85 with rustup (https://rustup.rs)" >&2; exit 1

$(DATAPLANE): $(CARGO) Cargo.toml Cargo.lock dataplane/Cargo.toml dataplane/build.rs $(wildcard dataplane/src/*.rs) $(wildcard dataplane/csrc/*) $(wildcard proto/swarmrec/v1/*.proto)
	@command -v $${CXX:-c++} >/dev/null || { echo "no C++ compiler ($${CXX:-c++}) for dataplane/csrc: install one (Debian: apt-get install g++)" >&2; exit 1; }
	$(CARGO) build --release --locked
	@touch $(DATAPLANE)

dataplane: $(DATAPLANE)

dataplane-test: $(DATAPLANE)
	$(CARGO) fmt --check
	$(CARGO) clippy --release --locked -- -D warnings
	$(CARGO) test --release --locked

unit: $(STAMP)
	$(BIN)/python -m pytest tests/unit -q

lint: $(STAMP)
	$(BIN)/ruff check .

typecheck: $(STAMP)
	$(BIN)/mypy

proto: $(STAMP)
	$(BIN)/python proto/generate.py

check-proto: $(STAMP)
	$(BIN)/python proto/generate.py --check

contracts: $(STAMP)
	$(BIN)/python -m swarmrec.services.contracts
	$(BIN)/python -m swarmrec.layers --figure docs/figures/architecture.png

bench: $(STAMP) $(DATAPLANE)
	$(BIN)/python bench/bench_offline.py --out bench/results/offline.json
	$(BIN)/python bench/bench_swarm.py --out bench/results/swarm.json
	$(BIN)/python bench/bench_cpu.py --data-plane both --zenoh-runtime both --out bench/results/swarm_cpu.json
	$(BIN)/python bench/bench_dataplane.py --out bench/results/dataplane.json
	$(BIN)/python bench/tie_rule.py --out bench/results/tie_rule.json
	$(BIN)/python bench/bench_detector.py --out bench/results/detector.json
	$(BIN)/python bench/bench_landmarks.py --out bench/results/landmarks.json
	$(BIN)/python bench/bench_compose.py --rebuild-base --out bench/results/compose.json
	$(BIN)/python bench/bench_gateway.py --out bench/results/gateway.json
	$(BIN)/python bench/bench_tls.py --out bench/results/tls.json
	$(BIN)/python bench/bench_scale.py --out bench/results/scale.json --plot docs/figures/scale.png
	$(BIN)/python bench/bench_links.py --out bench/results/links.json
	$(BIN)/python bench/bench_mesh.py --out bench/results/mesh.json --plot docs/figures/mesh_hops.png
	$(BIN)/python bench/bench_elastic.py --out bench/results/elastic.json
	$(BIN)/python bench/bench_scale.py --robots 100,50,25,10 --rules off,greedy,pack --out bench/results/scale_rules.json --plot docs/figures/scale_rules.png
	$(BIN)/python bench/bench_balance_bound.py --out bench/results/balance_bound.json --plot docs/figures/balance_bound.png
	$(BIN)/python bench/bench_vpr.py --out bench/results/vpr.json
	$(BIN)/python bench/bench_vpr_generalise.py --out bench/results/vpr_generalise.json
	$(BIN)/python bench/bench_vpr_live.py --out bench/results/vpr_live.json --plot docs/figures/vpr_live.png
	$(BIN)/python bench/bench_slam.py --out bench/results/slam.json --plots docs/figures
	$(BIN)/python bench/bench_slam_live.py --out bench/results/slam_live.json

images: $(STAMP)
	PYTHON=$(BIN)/python deploy/build.sh

swarm-up: images
	$(BIN)/swarmrec compose up --robots $(ROBOTS) --out $(COMPOSE_OUT)

swarm-run: $(STAMP)
	$(BIN)/swarmrec run --attach $(COMPOSE_OUT)

swarm-down: $(STAMP)
	$(BIN)/swarmrec compose down --out $(COMPOSE_OUT)

# The cluster runs a kubelet and containerd: these targets run as root (CI does).
k8s-up: images
	deploy/k8s/cluster-up.sh
	deploy/k8s/load-images.sh

k8s-apply: $(STAMP)
	$(BIN)/swarmrec k8s secrets --overlay $(K8S_OVERLAY) --kubectl $(KUBECTL)
	$(KUBECTL) apply --server-side --force-conflicts -k $(K8S_OVERLAY)

k8s-run: $(STAMP)
	$(BIN)/swarmrec run --deployment k8s --robots 3 --frames 600 --kubectl $(KUBECTL) --out runs/k8s-run

k8s-down:
	deploy/k8s/cluster-down.sh

clean:
	rm -rf $(VENV) .venv-train runs .pytest_cache .mypy_cache .ruff_cache target deploy/.bin
