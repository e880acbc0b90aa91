# Two entry points that need no set-up: "make demo" and "make test".
# Both build .venv with python3.11 (else python3) and pip-install this package with its test
# extras; the stamp file makes re-runs fast (it is rebuilt when the package sources change).

PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV := .venv
VENV_PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# "make demo" starts tracker_node on loopback DDS in its own domain and replays a bundled bag
# into it (a mesh-hand dev bag, see bags/README.md; never one of bags/mesh_test).
DEMO_BAG ?= bags/mesh_dev/rotate
DEMO_DOMAIN_ID ?= 74
# Tests use DDS on loopback only, in their own domain.
TEST_DOMAIN_ID ?= 73
LOOPBACK_PROFILE := $(CURDIR)/hand_sog_tracker/data/fastdds_loopback.xml

SOURCES := setup.py setup.cfg package.xml $(wildcard config/*.yaml) \
	$(shell find hand_sog_tracker -name '*.py' -o -name '*.xml' 2>/dev/null)

DOCS_STAMP := $(VENV)/.docs-installed
DOCS_OUT := doc/_build/html

.PHONY: demo test docs venv clean

venv: $(STAMP)

$(VENV_PY):
	$(PYTHON) -m venv $(VENV)

$(STAMP): $(SOURCES) | $(VENV_PY)
	$(VENV_PY) -m pip install --quiet --disable-pip-version-check '.[test]'
	touch $@

demo: $(STAMP)
	FASTRTPS_DEFAULT_PROFILES_FILE=$(LOOPBACK_PROFILE) ROS_DOMAIN_ID=$(DEMO_DOMAIN_ID) \
		$(VENV)/bin/hand_sog_demo $(DEMO_BAG) --domain-id $(DEMO_DOMAIN_ID)

test: $(STAMP)
	FASTRTPS_DEFAULT_PROFILES_FILE=$(LOOPBACK_PROFILE) ROS_DOMAIN_ID=$(TEST_DOMAIN_ID) \
		$(VENV_PY) -m pytest -q test

# The documentation site (Sphinx + MyST, the layout rosdoc2 builds): warnings are errors.
$(DOCS_STAMP): $(STAMP) setup.py
	$(VENV_PY) -m pip install --quiet --disable-pip-version-check '.[docs]'
	touch $@

docs: $(DOCS_STAMP)
	$(VENV_PY) -m sphinx -b html -W --keep-going -q doc $(DOCS_OUT)
	@echo "documentation: $(DOCS_OUT)/index.html"

clean:
	rm -rf $(VENV) build *.egg-info doc/_build
