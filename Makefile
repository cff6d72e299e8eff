# texelbake: `make demo` and `make test` are the two commands a newcomer needs.
SHELL := /bin/bash
VENV  := .venv
PY    := $(VENV)/bin/python
PIP   := $(VENV)/bin/pip
STAMP := $(VENV)/.installed
APT_PACKAGES := libusb-1.0-0 libgl1 libegl1 libopengl0 libx11-6 libudev1 libidn2-0 libgmp10 libgomp1 redis-server docker-compose \
	chromium chromium-driver
#: the dashboard's sources: a change rebuilds web/dist (and a schema change regenerates its client)
WEB_SRC := web/package.json web/package-lock.json web/index.html web/vite.config.ts web/tsconfig.json \
	$(shell find web/src -type f ! -name schema.d.ts 2>/dev/null) $(shell find services schemas -name '*.py' 2>/dev/null)
WEB_STAMP := web/dist/.built

.PHONY: setup demo test test-fast lint bench scenes addon clean

setup: $(STAMP) $(WEB_STAMP)
	@bash scripts/dcc-venv.sh >/dev/null  # Blender (bpy) for the dcc tests, cached in ~/.cache/texelbake

# Re-runs only when pyproject.toml changes: a second `make setup` does nothing.
$(STAMP): pyproject.toml scripts/apt-deps.sh
	bash scripts/apt-deps.sh $(APT_PACKAGES)
	test -x $(PY) || python3.11 -m venv $(VENV)
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[dev]'
	touch $(STAMP)

# The dashboard (web/): npm ci from the lockfile, the typed client generated from the API's
# OpenAPI schema, type-checked and bundled into web/dist, which the API serves at /.
# Node and npm: the machine's (nodesource), else Debian's.
$(WEB_STAMP): $(STAMP) $(WEB_SRC)
	command -v npm >/dev/null || bash scripts/apt-deps.sh nodejs npm
	$(PY) scripts/export_openapi.py web/openapi.json
	cd web && npm ci --no-audit --no-fund && npm run build
	touch $(WEB_STAMP)

demo: setup
	$(VENV)/bin/texelbake demo --out demo_out

test: setup
	$(PY) -m pytest -q -p no:cacheprovider --timeout=900 --durations=25 -n 2 --dist loadgroup

test-fast: setup
	$(PY) -m pytest -q -x -m "not service and not browser and not slow" -n 2 --dist loadgroup

lint: setup
	$(VENV)/bin/ruff check texelbake schemas farm texelbake_client workers services tests benchmarks blender scripts
	$(VENV)/bin/mypy texelbake texelbake_client blender/texelbake_submit/client.py

# The Blender add-on as an installable extension zip: build/texelbake_submit-<version>.zip
# (Blender: Edit > Preferences > Get Extensions > Install from Disk).
addon:
	python3.11 scripts/build_addon.py -o build

# Each benchmark prints a table (time beside error) and writes JSON; minutes, not for CI.
bench: setup
	mkdir -p bench_out
	$(PY) benchmarks/raycast.py --json bench_out/raycast.json
	$(PY) benchmarks/brdf_throughput.py --json bench_out/brdf.json
	$(PY) benchmarks/column_sampling.py --json bench_out/column_sampling.json
	$(PY) benchmarks/avis_methods.py --json bench_out/avis_methods.json
	$(PY) benchmarks/bake.py --scene cylinder --size full --json bench_out/bake.json
	$(PY) benchmarks/btf.py --synthetic --json bench_out/btf.json
	$(PY) benchmarks/render.py --scene cylinder --scene-size full --btf \
		--json bench_out/render_cylinder.json
	$(PY) benchmarks/fuzz_uploads.py --cases 2000 --json bench_out/fuzz_uploads.json
	$(PY) benchmarks/dashboard.py --json bench_out/dashboard.json

scenes: setup
	$(VENV)/bin/texelbake scenes all -o build/scenes --size small
	$(VENV)/bin/texelbake scenes all -o build/scenes --size full

clean:
	rm -rf $(VENV) demo_out bench_out build web/dist web/node_modules
