# The two commands of the README. Both create .venv and install the pinned dependencies when needed.
#   make demo   renders the bundled sample model (the main job) into out/
#   make test   runs the test suite
.PHONY: demo test env lint

export PYOPENGL_PLATFORM ?= egl

env:
	@bash scripts/setup_env.sh

demo: env
	.venv/bin/fruxel-render --mode both --out out

test: env
	.venv/bin/python -m pytest

lint: env
	.venv/bin/ruff check .
