# vpr-notebooks: two commands on a fresh machine with only python3:
#   make reproduce   execute the notebook sequence on the synthetic data, write reports/
#   make test        pytest + nbval (strict) over every notebook
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
PROFILE ?= reproduce
NBVAL  := --nbval --nbval-current-env --nbval-sanitize-with notebooks/sanitize.cfg --nbval-cell-timeout 600

.PHONY: venv test test-fast lint reproduce pretrain notebook lab bench clean assignments

venv: $(STAMP)

$(STAMP): environment.txt pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -r environment.txt
	$(BIN)/python -m pip install -q --no-deps --no-build-isolation -e .
	touch $(STAMP)

# The browser test needs Debian's chromium (.ci/run installs it); without it the test is skipped, with a note.
lint: venv
	$(BIN)/ruff check

test: venv lint
	@test -x /usr/bin/chromium || echo "note: /usr/bin/chromium is missing, so the JupyterLab browser test is skipped (sudo apt-get install -y chromium)"
	VPR_NB_ALLOW_SKIP_BROWSER=$$(test -x /usr/bin/chromium && echo 0 || echo 1) $(BIN)/python -m pytest -p no:cacheprovider -q tests notebooks $(NBVAL)

# re-execute notebooks in place for committing: make notebook NB=06 (or NB="03 06"); syncs the jupytext
# pair first and strips widget state (python -m vpr_nb.authoring)
notebook: venv
	@test -n "$(NB)" || { echo 'say which notebooks: make notebook NB=06 (or NB="03 06")'; exit 2; }
	$(BIN)/python -m vpr_nb.authoring $(foreach n,$(NB),$(wildcard notebooks/$(n)_*.ipynb))

test-fast: venv
	$(BIN)/python -m pytest -p no:cacheprovider -q tests -m "not slow"

reproduce: venv
	$(BIN)/python -m vpr_nb.report --profile $(PROFILE) --out reports

# re-make the course backbone (data_fixtures/course_backbone.pt + .json), about 6 min on 2 cores
pretrain: venv
	$(BIN)/python -m vpr_nb.pretrain

assignments: venv
	$(BIN)/python -m vpr_nb.assignments generate notebooks assignments

lab: venv
	$(BIN)/jupyter lab notebooks $$(test "$$(id -u)" = 0 && echo --allow-root)

# every bench runs even if one fails (a failure is a broken invariant or a ratio, never absolute time);
# the failed ones are listed at the end and make the target fail
bench: venv
	@failed=""; for f in bench/bench_*.py; do echo "== $$f"; $(BIN)/python $$f --quick || failed="$$failed $$f"; done; \
	if [ -n "$$failed" ]; then echo "bench failures:$$failed"; exit 1; fi; echo "all benches ran"

clean:
	rm -rf reports assignments .pytest_cache
