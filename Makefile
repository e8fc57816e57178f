# Two entry points (see README): `make demo` and `make test`.
# Both create .venv with Python >= 3.12 (pyenv picks 3.12.1 from .python-version) and install ambfit.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test test-fast install data paper notebooks clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 12) else "ambfit needs Python >= 3.12; found " + sys.version.split()[0] + " (install 3.12 or set PYTHON=python3.12)")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	@mkdir -p reports/demo
	$(BIN)/ambfit identify data/paper_table2.csv --json reports/demo/identify.json
	$(BIN)/ambfit identify data/paper_table2.csv --method closed-form --json reports/demo/identify_closed_form.json

test: $(STAMP)
	$(BIN)/ruff check ambfit tests benchmarks notebooks
	$(BIN)/python -m pytest -q -n 2

# The tests without the long ones (notebooks, the README's commands, two-worker runs): for a developer's loop.
test-fast: $(STAMP)
	$(BIN)/ruff check ambfit tests benchmarks notebooks
	$(BIN)/python -m pytest -q -n 2 -m "not slow"

# The seed paper's Tables 1-4 and Figs. 2, 3, 5 rerun on the rig, side by side with the paper (about 6 min).
paper: $(STAMP)
	$(BIN)/ambfit paper --out reports/paper --replicates 200 --seed 0

# Opens the notebooks in JupyterLab (installs the `notebooks` extra first); figures show inline.
notebooks: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[notebooks]'
	$(BIN)/jupyter lab notebooks/

# Regenerates the bundled default data (the command is also recorded in data/README.md).
data: $(STAMP)
	$(BIN)/ambfit origin-search --iterations 10 --seed 2 --experiment table2 --out data/paper_table2.csv --json data/paper_table2.search.json --truth data/paper_table2.truth.json

clean:
	rm -rf $(VENV) .pytest_cache reports/demo
