# deckland: two commands do all set-up (README): `make run` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.deckland-installed
RAY_STAMP := $(VENV)/.deckland-ray-installed
PKGS := $(sort $(wildcard src/*/setup.py))
SCENARIO ?= paper

.PHONY: setup setup-ray accel run test test-sitl lint golden bench clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# Re-installs only when requirements.txt or a package's setup.py/package.xml changed.
$(STAMP): $(PY) requirements.txt $(PKGS) $(wildcard src/*/package.xml)
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-deps $(foreach p,$(PKGS),-e $(dir $(p)))
	touch $(STAMP)

# deckland_interfaces, the rosidl messages: a standard ament_cmake package (colcon builds it on
# a ROS 2 install), built here with cmake against the ros-jazzy-* wheels and installed into the
# venv prefix: the Python package lands in site-packages and the libraries in .venv/lib, which
# the wheels' start-up hook already puts on the library path, so it imports with no environment
# variables. The wheels need four workarounds (FACTS.md "Custom messages"):
#  1. the generator and ament CMake wheels their metadata leaves out: requirements.txt;
#  2. AMENT_PREFIX_PATH and CMAKE_PREFIX_PATH = the venv, where the wheels put share/ and lib/;
#  3. their share/*/cmake/*__rosidl_generator_pyExport.cmake name the wheel builder's Python and
#     numpy include directories (/opt/python/cp311-cp311/...): rewritten to this interpreter's
#     (the whole value is replaced, so a second run changes nothing);
#  4. cmake and a C/C++ compiler: the machine's cmake, or PyPI's (< 4) in the venv if it has none.
# Rebuilt only when a message, CMakeLists.txt, package.xml or requirements.txt changed; the
# previous install (its install manifest and package directories) is removed first, so a
# deleted message leaves nothing behind. The build log is build/deckland_interfaces/build.log.
IFACE := src/deckland_interfaces
IFACE_BUILD := build/deckland_interfaces
IFACE_STAMP := $(VENV)/.deckland-interfaces-built
IFACE_MANIFEST := $(VENV)/.deckland-interfaces-manifest
IFACE_SRC := $(IFACE)/CMakeLists.txt $(IFACE)/package.xml \
	$(sort $(wildcard $(IFACE)/msg/*.msg $(IFACE)/srv/*.srv))
VENV_ABS = $(abspath $(VENV))
ROS_BUILD_ENV = AMENT_PREFIX_PATH=$(VENV_ABS) CMAKE_PREFIX_PATH=$(VENV_ABS) \
	PATH=$(VENV_ABS)/bin:$$PATH

$(IFACE_STAMP): $(IFACE_SRC) requirements.txt | $(STAMP)
	@command -v cmake >/dev/null || test -x $(VENV)/bin/cmake \
		|| $(PY) -m pip install --quiet 'cmake>=3.22,<4'
	@pyinc=$$($(PY) -c 'import sysconfig; print(sysconfig.get_paths()["include"])'); \
	npinc=$$($(PY) -c 'import numpy; print(numpy.get_include())'); \
	test -f "$$pyinc/Python.h" || { echo "Python headers missing ($$pyinc): install the" \
		"Python headers (python3-dev)" >&2; exit 1; }; \
	sed -i -E "s|(INTERFACE_INCLUDE_DIRECTORIES \")[^\"]*include/python3[^\"]*\"|\1$$pyinc;$$npinc\"|" \
		$(VENV)/share/*/cmake/*__rosidl_generator_pyExport.cmake
	@if [ -f $(IFACE_MANIFEST) ]; then xargs -d '\n' rm -f < $(IFACE_MANIFEST); fi
	@rm -rf $(VENV)/lib/python3*/site-packages/deckland_interfaces* \
		$(VENV)/include/deckland_interfaces $(VENV)/share/deckland_interfaces
	@rm -rf $(IFACE_BUILD) $(IFACE_STAMP) && mkdir -p $(IFACE_BUILD)
	@echo "building deckland_interfaces (log: $(IFACE_BUILD)/build.log)"
	@( $(ROS_BUILD_ENV) cmake -S $(IFACE) -B $(IFACE_BUILD) -DCMAKE_INSTALL_PREFIX=$(VENV_ABS) \
		-DPython3_EXECUTABLE=$(VENV_ABS)/bin/python -DBUILD_TESTING=OFF \
	&& $(ROS_BUILD_ENV) cmake --build $(IFACE_BUILD) --parallel 2 \
	&& $(ROS_BUILD_ENV) cmake --install $(IFACE_BUILD) ) > $(IFACE_BUILD)/build.log 2>&1 \
	|| { tail -n 40 $(IFACE_BUILD)/build.log; exit 1; }
	@cp $(IFACE_BUILD)/install_manifest.txt $(IFACE_MANIFEST)
	@$(PY) -c 'import deckland_interfaces.msg as m; assert m.__file__, "not built"'
	touch $(IFACE_STAMP)

setup: $(STAMP) $(IFACE_STAMP)

# The optional Ray backend (campaigns on a cluster): its tests need it, `make run` does not.
$(RAY_STAMP): $(STAMP) requirements-ray.txt
	$(PY) -m pip install --quiet -r requirements-ray.txt
	touch $(RAY_STAMP)

setup-ray: $(RAY_STAMP)

# The compiled cores for batch runs (deckland.batch.accel, mypyc): rebuilt only when a compiled
# source changed. Campaigns run ~3x faster with them; they fall back to the sources without.
accel: setup
	@$(VENV)/bin/deckland accel status >/dev/null 2>&1 || $(VENV)/bin/deckland accel build

run: setup
	$(VENV)/bin/deckland up --scenario $(SCENARIO) --record runs/latest

# The suite on two workers, then the whole missions against the wall clock (marker `solo`) alone.
test: setup setup-ray accel
	DECKLAND_REQUIRE_ACCEL=1 $(PY) -m pytest test -n 2 --dist loadgroup -m 'not sitl_mission and not solo'
	DECKLAND_REQUIRE_ACCEL=1 $(PY) -m pytest test -m 'solo and not sitl_mission'

# Whole missions through the real PX4 / ArduPilot SITL (minutes each, needs a quiet machine).
test-sitl: setup accel
	$(PY) -m pytest test -m sitl_mission

lint: setup
	$(VENV)/bin/ruff check .
	$(PY) -m mypy

# Deliberate only (never run by tests): fly the reference landing and rewrite the golden bag.
golden: setup
	$(PY) test/support/golden.py record test/fixtures/golden_paper

clean:
	rm -rf $(VENV) runs build install log .pytest_cache
