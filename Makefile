# The two commands of the README. Both create .venv and install the pinned dependencies when needed.
#   make demo   the main job on the bundled photos: SSZ (the default model, told each photo's camera) predicts
#               their models, which fruxel-render draws beside each photo and its ground truth: a furnished room
#               from a hand-held height into out/room_both.png, the robot's view of a flat room into
#               out/photo_both.png
#   make test   runs the test suite's fast tier (minutes on 2 cores)
# Also: make test-slow (the tests marked slow: training runs, DDP, the robot drives; CI runs both tiers), make lint,
# make assets (the simulator's asset pack, assets/pack, from Debian and PyPI packages cached in assets/cache).
.PHONY: demo test test-slow env lint assets

export PYOPENGL_PLATFORM ?= egl

env:
	@bash scripts/setup_env.sh

demo: env
	.venv/bin/fruxel-render fruxel/data/room.png --truth fruxel/data/room_truth.npz --pitch 5.7 --roll 4.6 --height 1.59 --mode both --out out
	.venv/bin/fruxel-render fruxel/data/photo.png --truth fruxel/data/photo_truth.npz --pitch 10 --height 1.0 --mode both --out out

test: env
	.venv/bin/python -m pytest -m "not slow"

test-slow: env
	.venv/bin/python -m pytest -m slow

lint: env
	.venv/bin/ruff check .

assets: env
	.venv/bin/fruxel-sim assets --sources assets/cache --out assets/pack --replace --workers 2
