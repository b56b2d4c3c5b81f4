# Two commands do all set-up on a fresh machine: `make demo` and `make test`.
# Set-up is idempotent: .venv is (re)built only when pyproject.toml or constraints.txt changed.
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed
export PREFECT_SERVER_ANALYTICS_ENABLED := false
# OpenMP threads (numba kernels, torch) sleep instead of spinning while they wait: on a shared 2-core
# machine spinning threads steal the core the other worker needs.
export OMP_WAIT_POLICY := PASSIVE

.PHONY: setup demo test test-slow bench docs clean system-deps

setup: $(STAMP)

# open3d needs Debian's libusb-1.0-0 at import time; the viewer's browser test drives Debian's chromium (Playwright's
# own browser download is not reachable from every machine).
system-deps:
	@if ! command -v chromium >/dev/null 2>&1; then \
	  if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	    echo "installing Debian package chromium (the headless browser of the viewer's test)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	  else \
	    echo "warning: chromium is not installed (apt-get install chromium); the viewer's browser test will be skipped" >&2; \
	  fi; \
	fi
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	    echo "installing Debian package libusb-1.0-0 (needed by open3d)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	  else \
	    echo "error: open3d needs the system library libusb-1.0-0; install it (apt-get install libusb-1.0-0) and re-run" >&2; exit 2; \
	  fi; \
	fi

$(STAMP): pyproject.toml constraints.txt | system-deps
	@test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q --upgrade pip wheel setuptools
	$(VENV)/bin/python -m pip install -q -c constraints.txt torch==2.13.0
	$(VENV)/bin/python -m pip install -q -c constraints.txt -e '.[test,docs]'
	$(VENV)/bin/python -m pip install -q -c constraints.txt --no-deps nuscenes-devkit==1.2.0
	$(VENV)/bin/python -m pip install -q -c constraints.txt --no-deps asam-qc-opendrive==1.0.0
	@touch $(STAMP)

demo: setup
	$(VENV)/bin/omniscs demo

test: setup
	$(VENV)/bin/python -m pytest -n 2 -q

test-slow: setup
	$(VENV)/bin/python -m pytest -n 2 -q -m slow

# the documentation site into site/ (the Results pages are generated from reports/ by docs/gen_results.py)
docs: setup
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/python -m mkdocs build --strict --site-dir site

bench: setup
	$(VENV)/bin/omniscs bench world
	$(VENV)/bin/omniscs bench render

clean:
	rm -rf $(VENV) omniscs-data .pytest_cache site
