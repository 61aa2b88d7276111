"""Make ``model.safetensors`` here: the ``tiny`` preset (32^3 cells from 64^2 images) reading the camera, trained
on the CPU for 25 minutes on the flat world's rooms from any camera, for the test that a camera declared higher moves
the predicted floor away (tests/train/test_camera_floor.py). A trained network, not random weights: only training
ties the camera inputs to where the floor is.

    .venv/bin/python tests/data/camera_tiny/make_model.py [--out-run /tmp/runs/camera_tiny] [--seconds 1500]

The run folder goes outside the repository; the model file (float16, about 0.3 MB) is copied here.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent


def config(seconds: int) -> dict:
    """The run's config: the tiny preset with the flat world's classes and rooms from any camera."""
    from fruxel.classes import DEFAULT_CLASSES

    return {"preset": "tiny", "model": {"classes": DEFAULT_CLASSES.to_dict()},
            "data": {"world": "flat", "camera": "any", "workers": 1},
            "run": {"steps": 200000, "time_limit": seconds, "eval_every": 100000, "checkpoint_every": 2000}}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out-run", type=Path, default=Path(tempfile.gettempdir()) / "runs" / "camera_tiny")
    p.add_argument("--seconds", type=int, default=1500)
    args = p.parse_args()
    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as f:
        json.dump(config(args.seconds), f)
    cmd = [sys.executable, "-m", "fruxel.cli.train", "--config", f.name, "--out", str(args.out_run), "-q"]
    if subprocess.run(cmd).returncode != 0:
        return 1
    shutil.copyfile(args.out_run / "model.safetensors", HERE / "model.safetensors")
    print(f"wrote {HERE / 'model.safetensors'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
