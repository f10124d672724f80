# Two commands on a fresh machine:  `make demo` (install + run the pipeline on the embedded default data)
#                                   `make test` (install + lint + the test suite)
PY ?= python3
VENV ?= .venv
TORCH_INDEX ?=
BIN := $(VENV)/bin
export MUJOCO_GL ?= egl
export DVC_NO_ANALYTICS = 1

.PHONY: install test demo lint docs bench clean

$(BIN)/.installed: pyproject.toml constraints.txt
	$(PY) -m venv $(VENV)
	# torch first, pinned; TORCH_INDEX picks the build (https://download.pytorch.org/whl/cpu: CPU; .../whl/cuXXX:
	# CUDA); unset, pip's own index and configuration decide (on the project's machines: the CPU build on disk)
	$(BIN)/pip install -q torch==2.13.0 $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
	$(BIN)/pip install -q -c constraints.txt -e ".[all,dev,docs,dask,pusht,kitchen]"
	# Push-T's environment without its opencv-python requirement (adlpipe has opencv-python-headless)
	$(BIN)/pip install -q --no-deps gym-pusht==0.1.8
	touch $@

install: $(BIN)/.installed

lint: install
	$(BIN)/ruff check adlpipe tests bench examples tools pipelines
	$(BIN)/mypy
	# the other commit hooks on every tracked file (.pre-commit-config.yaml: whitespace, file ends, YAML / TOML,
	# merge markers, large files); ruff and mypy just ran. In a git checkout only (pre-commit reads git's file list).
	@if [ -d .git ]; then SKIP=ruff,mypy PATH="$(abspath $(BIN)):$$PATH" $(BIN)/pre-commit run --all-files; fi

docs: install
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict -q -d site

test: install lint docs
	$(BIN)/python -m pytest -q

demo: install
	@test -d .git || (echo "make demo needs a git checkout (dvc)"; exit 1)
	# record, ingest, split; then the three trainings at once (one thread each, params.yaml), then the rest
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/dvc repro split
	PATH="$(abspath $(BIN)):$$PATH" ADLPIPE_SIDE_BY_SIDE=3 $(BIN)/python pipelines/train_side_by_side.py train@
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/dvc repro
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/dvc metrics show

bench: install
	$(BIN)/python bench/ingest.py
	$(BIN)/python bench/infer.py

clean:
	rm -rf $(VENV) data/bags data/*.h5 data/split.json models metrics reports
