# Two commands do all set-up on a fresh machine:  make demo  and  make test.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin

.PHONY: demo up test test-fast bench bench-quick lock clean

$(BIN)/nwr: pyproject.toml requirements.lock
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements.lock
	$(BIN)/python -m pip install --quiet --no-deps -e .
	touch $(BIN)/nwr

demo: $(BIN)/nwr   ## the whole pipeline on a scripted 30 s touch session, then the per-touch table
	$(BIN)/nwr demo

up: $(BIN)/nwr     ## every service as its own process until Ctrl-C
	$(BIN)/nwr up

test: $(BIN)/nwr   ## every test, the multi-process ones included
	$(BIN)/python -m pytest

test-fast: $(BIN)/nwr  ## the fast tests only
	$(BIN)/python -m pytest -m "not slow and not e2e"

bench: $(BIN)/nwr  ## measure the reflex path of the real pipeline (several minutes); writes bench/<time>/
	$(BIN)/nwr bench

bench-quick: $(BIN)/nwr  ## the benchmark's smoke run (under a minute)
	$(BIN)/nwr bench --quick

lock:              ## re-pin requirements.lock from the current environment
	$(BIN)/python -m pip freeze --exclude-editable | grep -v '^-e' > requirements.lock.new
	{ echo '# Exact versions for repeatable installs. Regenerate with: make lock'; cat requirements.lock.new; } > requirements.lock
	rm requirements.lock.new

clean:
	rm -rf $(VENV) build *.egg-info
