# The two commands of the README. Each creates .venv and installs pinned dependencies itself.
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip install -q --disable-pip-version-check -c constraints.txt

.PHONY: reproduce test clean

$(VENV)/bin/python:
	python3 -m venv $(VENV)

$(VENV)/.runtime: pyproject.toml constraints.txt | $(VENV)/bin/python
	$(PIP) -e .
	touch $@

$(VENV)/.test: $(VENV)/.runtime lsdyna-requirements.txt
	$(PIP) -e '.[test,slurm,team]'
	$(PIP) --no-deps -r lsdyna-requirements.txt
	touch $@

## reproduce: run the whole workflow on the embedded default campaign
reproduce: $(VENV)/.runtime
	$(PY) -m crashfuse.reproduce

## test: run the test suite
test: $(VENV)/.test
	$(PY) -m pytest -q -n 2 --dist loadgroup --durations=8

clean:
	rm -rf $(VENV) .snakemake mlflow.db mlartifacts
	find results -mindepth 1 -maxdepth 1 ! -name README.md -exec rm -rf {} +
