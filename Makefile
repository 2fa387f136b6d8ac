# The two commands of the README: `make demo` (the main job) and `make test`. Both set up .venv first.
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.pivla-setup
DEMO_STAMP := $(VENV)/.pivla-setup-demo

.PHONY: setup setup-demo setup-libero setup-openpi-client test test-slow demo demo-quick firmware clean

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh
	touch $(STAMP)

# the demo needs training and the twin only: pivla[train,sim] installs in about half the time of [all,dev]
setup-demo: $(DEMO_STAMP)

$(DEMO_STAMP): pyproject.toml scripts/setup.sh
	PIVLA_EXTRAS=train,sim bash scripts/setup.sh
	touch $(DEMO_STAMP)

setup-libero: $(STAMP)
	bash scripts/setup-libero.sh

# openpi's published client in a venv of its own (it pins numpy<2): the serving tests run it against pivla's server
setup-openpi-client:
	bash scripts/setup-openpi-client.sh

test: setup setup-libero setup-openpi-client
	$(VENV)/bin/ruff check src tests
	$(PY) -m pytest -q

test-slow: setup setup-libero setup-openpi-client
	$(PY) -m pytest -q -m slow

demo: setup-demo
	$(VENV)/bin/pivla demo --out runs/demo

demo-quick: setup-demo
	$(VENV)/bin/pivla demo --out runs/demo-quick --quick

firmware:
	$(MAKE) -C firmware

clean:
	rm -rf runs build dist *.egg-info .venv-openpi
