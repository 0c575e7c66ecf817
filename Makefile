# Two commands do all the set-up on a fresh machine: `make demo` and `make test`.
# torch is the CPU build pinned in constraints.txt (this machine's pip finds it locally; elsewhere TORCH_INDEX).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP_FLAGS ?= -q --disable-pip-version-check
# where pip finds a CPU build of torch when its own configuration has none (on Linux PyPI's torch pulls
# several GB of CUDA packages): make demo TORCH_INDEX=https://download.pytorch.org/whl/cpu
TORCH_INDEX ?=
STAMP := $(VENV)/.installed

.PHONY: venv demo test lint format bench clean device-wheels device-sumo-scenes device-vocab device-keep

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install $(PIP_FLAGS) $(if $(TORCH_INDEX),--extra-index-url $(TORCH_INDEX)) -c constraints.txt -e ".[dev,sumo]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/trajeglish demo --out out/demo

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: $(STAMP)
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

test: lint
	$(PY) -m pytest -n 2 --durations=15 tests

bench: $(STAMP)
	$(VENV)/bin/trajeglish bench --out out/bench.json

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache

# ---- training on a lent GPU machine (scripts/device_train.sh; README "Training on a GPU machine")
# The machine has Python 3.12 (x86-64) with torch, numpy, pandas, matplotlib and tqdm, no network: these
# wheels are what generation and `import trajeglish_env` need besides (pygame-ce: highway-env imports it).
DEVICE_WHEELS ?= gymnasium==1.4.0 farama-notifications==0.0.6 pettingzoo==1.27.0 highway-env==1.12.1 \
	pygame-ce==2.5.8 protobuf==7.36.2
DEVICE_PLATFORMS := $(foreach n,2_28 2_27 2_17,--platform manylinux_$(n)_x86_64) \
	--platform manylinux2014_x86_64 --platform manylinux1_x86_64
device-wheels:
	rm -rf .whl && mkdir -p .whl
	$(PYTHON) -m pip download $(PIP_FLAGS) --no-deps --only-binary=:all: --python-version 3.12 \
		--implementation cp $(DEVICE_PLATFORMS) -d .whl $(DEVICE_WHEELS)
	@ls -l .whl && du -sh .whl

# SUMO's wheel (about 150 MB) cannot travel: SUMO scenes are made here and carried as DATA_IN=.devdata.
DEVICE_SUMO_SCENES ?= 80
device-sumo-scenes: $(STAMP)
	rm -rf .devdata/train/sumo .devdata/val/sumo
	$(VENV)/bin/trajeglish generate --quiet --source sumo --scenes $(DEVICE_SUMO_SCENES) --seed 2000 \
		--workers $$(nproc) --out .devdata/train/sumo
	$(VENV)/bin/trajeglish generate --quiet --source sumo --scenes 8 --seed 90002 --workers $$(nproc) \
		--out .devdata/val/sumo
	@du -sh .devdata

# The extended vocabulary the job would make (EXTEND=2048 with INIT=shipped), made here and carried in
# .devdata (93 KB): the call trains on it at once.
DEVICE_EXTEND ?= 2048
device-vocab: $(STAMP)
	mkdir -p .devdata
	$(VENV)/bin/trajeglish tokenizer extend --json --base shipped --size $(DEVICE_EXTEND) \
		--out .devdata/vocab_extended_$(DEVICE_EXTEND).npz > /dev/null
	@ls -l .devdata/vocab_extended_$(DEVICE_EXTEND).npz

# After a call: `make device-keep FROM=<the call's files_at>` keeps the results in runs/device/ and the
# folder the next call resumes from in .devrun/ (carry: [".whl", ".devrun"], RUN_IN=.devrun).
device-keep:
	@test -n "$(FROM)" && test -d "$(FROM)/resume" || { echo "usage: make device-keep FROM=<files_at of the call>"; exit 2; }
	rm -rf .devrun && cp -r "$(FROM)/resume" .devrun && chmod -R u+w .devrun
	mkdir -p runs/device && cp "$(FROM)"/*.* runs/device/ && chmod -R u+w runs/device
	@python3 -c 'import json; s = json.load(open("runs/device/summary.json")); print("step", s.get("step"), "of", s.get("steps_total"), "val_nll", s.get("val_nll"))'
