# The two commands of the README. Both create .venv and install the pinned dependencies when needed.
#   make demo   the main job on the bundled photo: SSZ predicts its model, which fruxel-render draws beside the
#               photo and its ground truth, into out/photo_both.png
#   make test   runs the test suite
#   make assets builds the simulator's asset pack (assets/pack) from Debian and PyPI packages, cached in assets/cache
.PHONY: demo test env lint assets

export PYOPENGL_PLATFORM ?= egl

env:
	@bash scripts/setup_env.sh

demo: env
	.venv/bin/fruxel-render fruxel/data/photo.png --truth fruxel/data/photo_truth.npz --mode both --out out

test: env
	.venv/bin/python -m pytest

lint: env
	.venv/bin/ruff check .

assets: env
	.venv/bin/fruxel-sim assets --sources assets/cache --out assets/pack --replace --workers 2
