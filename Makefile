# The README's two commands: `make demo` (main job) and `make test` (the suite).
# Both create .venv on first use; torch is pinned through constraints.txt.
PY      ?= python3
TEST_WORKERS ?= 2   # pytest-xdist processes; a test module stays in one (its Ray instance, its fixtures)
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed

# The public modules docs/api.md lists: on these, `make lint` also checks Google-style docstrings (every public
# name documented, every argument in Args, Returns and Raises where the code returns and raises).
# tests/test_api_docstrings.py checks that this list covers every name of api.md's table.
API_MODULES := parksim/camera parksim/device.py parksim/rig.py parksim/geometry.py parksim/ipm.py parksim/gaussians.py \
               parksim/render/__init__.py parksim/render/api.py parksim/render/projection.py \
               parksim/render/rasterize/__init__.py parksim/render/rasterize/reference.py \
               parksim/render/rasterize/constants.py parksim/data parksim/bundle.py parksim/sim.py \
               parksim/client.py parksim/frames.py parksim/env.py parksim/vehicle.py parksim/planners/__init__.py \
               parksim/planners/geometric.py parksim/planners/hybrid_astar.py parksim/planners/hybrid_parker.py \
               parksim/planners/reeds_shepp.py parksim/planners/scenario_planners.py \
               parksim/planners/scenario_runs.py parksim/planners/scenario_report.py parksim/scenarios/task.py \
               parksim/scenarios/make.py parksim/scenarios/pictures.py parksim/server/episodes.py parksim/recon/reconstruct.py parksim/recon/trainer.py \
               parksim/recon/config.py parksim/server/__init__.py parksim/server/app.py parksim/server/settings.py
DOC_RULES   := D,DOC102,DOC201,DOC202,DOC402,DOC403,DOC501

.PHONY: setup demo test lint clean

setup: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt -e ".[server,env,ray,test,colmap,dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/parksim demo -o out/demo

test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=25

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff check --preview --select $(DOC_RULES) $(API_MODULES)
	$(BIN)/mypy

clean:
	rm -rf out .pytest_cache
