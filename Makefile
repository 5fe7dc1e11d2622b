# Two commands on a fresh clone: `make synthesize` and `make test`.
SCENARIO ?= quadrotor_hill
# `make synthesize`'s worker processes: both cores of the machine it ships for (results do not
# depend on it; JOBS=1 runs everything in one process)
JOBS ?= 2
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: synthesize test readme bench demos record lint clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	@# setuptools' notice on every editable install ("Editable installation ... be careful with
	@# folders named like your package"): informational, about editable installs in general
	PYTHONWARNINGS='ignore:Editable installation' $(PY) -m pip install --quiet -e '.[test]'
	@touch $(STAMP)

synthesize: $(STAMP)
	$(PY) -m pipeline synthesize $(SCENARIO) --jobs $(JOBS)

# two workers; each scenario's session synthesis stays on one (xdist_group marks, tests/conftest.py),
# the groups handed out in collection order (conftest sorts the long syntheses first)
test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadgroup --no-loadscope-reorder

# the results blocks of README.md and docs/results.md, from the runs in reports/ (run
# `make synthesize SCENARIO=quadrotor_hill` and `SCENARIO=double_integrator` first)
readme: $(STAMP)
	$(PY) -m pipeline.runtime.readme_results reports/quadrotor_hill --write README.md
	$(PY) -m pipeline.runtime.readme_results reports/double_integrator --write docs/results.md

bench: $(STAMP)
	PYTHONWARNINGS='ignore:Editable installation' $(PY) -m pip install --quiet -e '.[bench]'
	$(PY) -m bench

demos: $(STAMP)
	$(PY) -m pipeline demos $(SCENARIO)

record: $(STAMP)
	$(PY) -m pipeline record $(SCENARIO)

lint: $(STAMP)
	$(PY) -m ruff check pipeline stages tests bench examples scenarios
	$(PY) -m ruff format --check pipeline stages tests bench examples scenarios
	$(VENV)/bin/lint-imports
	$(VENV)/bin/mypy

clean:
	rm -rf $(VENV) reports/*/ .pytest_cache build *.egg-info
