# vpr-notebooks. On a fresh machine with only python3 (3.11-3.13) and make:
#   make venv        the student environment (.venv: environment.txt + vpr_nb editable)
#   make lab         JupyterLab on the notebooks
#   make reproduce   execute the notebook sequence on the synthetic data, write reports/
#   make test        the developer environment (requirements-dev.txt) + ruff + pytest + nbval (strict)
#   make site        the course as a website, built locally into _site/html (no notebook executed)
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEV_STAMP := $(VENV)/.installed-dev
PROFILE ?= reproduce
# notebooks run at once by make reproduce (each kernel uses one torch thread; a notebook waits for those it reads)
JOBS   ?= 2
NBVAL  := --nbval --nbval-current-env --nbval-sanitize-with notebooks/sanitize.cfg --nbval-cell-timeout 600

# torch: on Linux without an NVIDIA GPU (no `nvidia-smi -L`), the CPU build from PyTorch's CPU index
# (about 190 MB instead of a CUDA build of several GB); elsewhere PyPI's build. Override with
#   make venv TORCH=cuda              PyPI's build (CUDA on Linux)
#   make venv TORCH=cpu               the CPU build even where a GPU is present
#   make venv TORCH_INDEX=<url>       another index for the CPU build (a mirror)
# torch is installed first with --no-deps (only torch itself comes from TORCH_INDEX); its own
# dependencies then come from PyPI with environment.txt, where the version is pinned.
ifeq ($(origin TORCH),undefined)
TORCH := $(shell if [ "$$(uname -s)" = Linux ] && ! nvidia-smi -L >/dev/null 2>&1; then echo cpu; else echo cuda; fi)
endif
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
TORCH_PIN   := $(shell sed -n 's/^torch==\([^ ]*\).*/\1/p' environment.txt)
# $(1): the venv's bin folder, $(2): the torch requirement, $(3): more pip options
define install_torch
	@case "$(TORCH)" in cpu|cuda) ;; *) echo "error: TORCH must be cpu or cuda, got '$(TORCH)'"; exit 2;; esac
	$(if $(filter cpu,$(TORCH)),$(1)/python -m pip install -q --no-deps --index-url $(TORCH_INDEX) $(3) "$(2)",@echo "torch: PyPI's build (TORCH=$(TORCH))")
endef

# The newest releases that resolve (tested on Python 3.13): `make test-newest PY=python3.13` builds
# NEWEST_VENV from pyproject.toml's unpinned dependencies under constraints-newest.txt and runs the tests
# there; `make newest-constraints PY=python3.13` re-resolves without constraints and rewrites that file.
PY          ?= python3.13
NEWEST_VENV ?= .venv-newest
TEST_PATHS  ?= tests notebooks $(NBVAL)

.PHONY: venv dev test site test-fast test-newest newest-venv newest-constraints lint reproduce pretrain notebook lab bench clean assignments

venv: $(STAMP)

dev: $(DEV_STAMP)

$(STAMP): environment.txt pyproject.toml setup.py
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(call install_torch,$(BIN),torch==$(TORCH_PIN))
	$(BIN)/python -m pip install -q -r environment.txt
	$(BIN)/python -m pip install -q --no-deps -e .
	$(BIN)/python -m vpr_nb.authoring --install-save-hook
	touch $(STAMP)

$(DEV_STAMP): $(STAMP) requirements-dev.txt
	$(BIN)/python -m pip install -q -r requirements-dev.txt
	touch $(DEV_STAMP)

# The browser test needs Debian's chromium (.ci/run installs it); without it the test is skipped, with a note.
# $(1): the bin folder of the environment to test
define run_tests
	$(1)/ruff check
	$(1)/lint-imports
	@test -x /usr/bin/chromium || echo "note: /usr/bin/chromium is missing, so the browser tests (JupyterLab, the site) are skipped (sudo apt-get install -y chromium)"
	VPR_NB_ALLOW_SKIP_BROWSER=$$(test -x /usr/bin/chromium && echo 0 || echo 1) $(1)/python -m pytest -p no:cacheprovider -q $(TEST_PATHS)
endef

lint: dev
	$(BIN)/ruff check

test: dev
	$(call run_tests,$(BIN))

newest-venv: $(NEWEST_VENV)/.installed-newest

$(NEWEST_VENV)/.installed-newest: constraints-newest.txt pyproject.toml setup.py
	test -x $(NEWEST_VENV)/bin/python || $(PY) -m venv $(NEWEST_VENV)
	$(call install_torch,$(NEWEST_VENV)/bin,torch,-c constraints-newest.txt)
	$(NEWEST_VENV)/bin/python -m pip install -q -c constraints-newest.txt -e ".[test]"
	touch $@

test-newest: newest-venv
	$(NEWEST_VENV)/bin/python -c "import sys, torch, numpy; print('python', sys.version.split()[0], 'torch', torch.__version__, 'numpy', numpy.__version__)"
	$(call run_tests,$(NEWEST_VENV)/bin)

newest-constraints:
	test -x $(NEWEST_VENV)/bin/python || $(PY) -m venv $(NEWEST_VENV)
	$(call install_torch,$(NEWEST_VENV)/bin,torch,--upgrade)
	$(NEWEST_VENV)/bin/python -m pip install -q --upgrade --upgrade-strategy eager -e ".[test]"
	{ echo "# The newest releases that resolved for \`pip install -e .[test]\` on Python $$($(NEWEST_VENV)/bin/python -c 'import platform; print(platform.python_version())'), $$(date -u +%F)"; \
	  echo "# (make newest-constraints PY=python3.13); used by make test-newest. torch: $(TORCH) build."; \
	  $(NEWEST_VENV)/bin/python -m pip freeze --exclude-editable | grep -v '^-e ' | sed 's/+[A-Za-z0-9.]*$$//' | LC_ALL=C sort -f; } > constraints-newest.txt
	touch $(NEWEST_VENV)/.installed-newest

# re-execute notebooks in place for committing: make notebook NB=06 (or NB="03 06"); syncs the jupytext
# pair first and strips widget state (python -m vpr_nb.authoring)
notebook: venv
	@test -n "$(NB)" || { echo 'say which notebooks: make notebook NB=06 (or NB="03 06")'; exit 2; }
	$(BIN)/python -m vpr_nb.authoring $(foreach n,$(NB),$(wildcard notebooks/$(n)_*.ipynb))

# the course as a website: README (home), the notebooks as stored (never executed), docs/, the package reference
# and the commands' --help, by Sphinx with warnings as errors (docs/site/build.py; tests/test_site.py builds it too);
# about 40 s on 2 cores. Prints where to open it: _site/html/index.html
site: dev
	$(BIN)/python docs/site/build.py --out _site

test-fast: dev
	$(BIN)/python -m pytest -p no:cacheprovider -q tests -m "not slow"

# make reproduce [NOTEBOOK=07] [STORE=off|DIR] [DASK=tcp://HOST:8786] [WORKERS=N]: finished fine-tunes are kept in
# reports/task-store (STORE), so a run started again after an interruption trains only what is missing;
# make reproduce NOTEBOOK=07 ARMS='cliques*' SEEDS=2: those arms and seeds alone, beside the committed numbers
# (vpr_nb.remake; docs/reproduction.md)
reproduce: venv
ifneq ($(ARMS)$(SEEDS),)
	@test -n "$(NOTEBOOK)" || { echo "error: ARMS and SEEDS need NOTEBOOK, e.g. make reproduce NOTEBOOK=07 ARMS='cliques*' SEEDS=2"; exit 2; }
	$(BIN)/python -m vpr_nb.kernels --run $(BIN)/python -m vpr_nb.remake $(NOTEBOOK) --arms '$(or $(ARMS),*)'$(if $(SEEDS), --seeds $(SEEDS))$(if $(WORKERS), --workers $(WORKERS))
else
	$(BIN)/python -m vpr_nb.report --profile $(PROFILE) --out reports --jobs $(JOBS)$(if $(NOTEBOOK), --notebook $(NOTEBOOK))$(if $(STORE), --store $(STORE))$(if $(DASK), --dask $(DASK))$(if $(WORKERS), --workers $(WORKERS))
endif

# re-make the course backbone (vpr_nb/weights/course_backbone.pt + .json), about 6 min on 2 cores
pretrain: venv
	$(BIN)/python -m vpr_nb.kernels --run $(BIN)/python -m vpr_nb.pretrain

assignments: venv
	$(BIN)/python -m vpr_nb.assignments generate notebooks assignments

lab: venv
	$(BIN)/python -m vpr_nb.kernels --run $(BIN)/jupyter lab notebooks $$(test "$$(id -u)" = 0 && echo --allow-root)

# every bench runs even if one fails (a failure is a broken invariant or a ratio, never absolute time);
# the failed ones are listed at the end and make the target fail
bench: dev
	@failed=""; for f in bench/bench_*.py; do echo "== $$f"; $(BIN)/python $$f --quick || failed="$$failed $$f"; done; \
	if [ -n "$$failed" ]; then echo "bench failures:$$failed"; exit 1; fi; echo "all benches ran"

clean:
	rm -rf reports assignments .pytest_cache _site
