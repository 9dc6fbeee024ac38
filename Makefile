# Two commands do all set-up on a fresh machine:  make demo  and  make test.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin

.PHONY: demo up test test-fast lint bench bench-quick lock clean

$(BIN)/nwr: pyproject.toml requirements.lock requirements-dev.lock
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements.lock -r requirements-dev.lock
	$(BIN)/python -m pip install --quiet --no-deps -e .
	touch $(BIN)/nwr

demo: $(BIN)/nwr   ## the whole pipeline on a scripted 30 s touch session, then the per-touch table
	$(BIN)/nwr demo

up: $(BIN)/nwr     ## every service as its own process until Ctrl-C
	$(BIN)/nwr up

test: lint        ## lint and types, then every test, the multi-process ones included
	$(BIN)/python -m pytest

# mypy checks the installed layout (nwr.common, nwr.services): a tree of links
# maps it onto common/ and services/, as the editable install does.
TYPECHECK := build/typecheck
lint: $(BIN)/nwr   ## ruff (style, bugs, imports) and mypy (types) over the code
	$(BIN)/ruff check .
	rm -rf $(TYPECHECK) && mkdir -p $(TYPECHECK)/nwr
	ln -s $(CURDIR)/common $(TYPECHECK)/nwr/common && ln -s $(CURDIR)/services $(TYPECHECK)/nwr/services
	cd $(TYPECHECK) && $(CURDIR)/$(BIN)/mypy --config-file $(CURDIR)/pyproject.toml --explicit-package-bases -p nwr

test-fast: $(BIN)/nwr  ## the fast tests only
	$(BIN)/python -m pytest -m "not slow and not e2e"

bench: $(BIN)/nwr  ## measure the reflex path, pinned to two CPUs then unpinned, and judge the targets; writes bench/<time>/
	$(BIN)/nwr bench --cpus 0-1 --also-unpinned

bench-quick: $(BIN)/nwr  ## the benchmark's smoke run (81-132 s on the shared 2-core machine, load 2.7-4.3)
	$(BIN)/nwr bench --quick

lock:              ## re-pin requirements.lock (runtime and tests) and requirements-dev.lock (tools) from .venv
	$(BIN)/python -m pip freeze --exclude-editable | grep -v '^-e' > lock.all
	sed -n 's/==.*//p' requirements-dev.lock | sed 's/^/^/; s/$$/==/' > lock.dev-names
	{ sed -n '1,/^# Regenerate/p' requirements-dev.lock; grep -i -f lock.dev-names lock.all; } > requirements-dev.lock.new
	{ echo '# Exact versions for repeatable installs (pip install -r requirements.lock). Regenerate with: make lock'; \
	  grep -v -i -f lock.dev-names lock.all; } > requirements.lock
	mv requirements-dev.lock.new requirements-dev.lock
	rm lock.all lock.dev-names

clean:
	rm -rf $(VENV) build *.egg-info
