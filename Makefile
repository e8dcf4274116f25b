# The README's two commands: `make demo` and `make test`. Both set up first.
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.setup-done

.PHONY: setup test demo clean

setup: $(STAMP)

$(STAMP): pyproject.toml constraints.txt scripts/setup.sh clients/node/package-lock.json
	bash scripts/setup.sh
	touch $@

test: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy
	$(PY) -m pytest -q -p no:cacheprovider tests

demo: setup
	$(VENV)/bin/dtx demo --out out/demo

clean:
	rm -rf $(VENV) out
