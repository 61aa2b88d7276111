"""Session-wide test settings: headless OpenGL and quiet Warp, set before any test imports pyrender or warp."""

import os

# pyrender picks its OpenGL platform at import time; tests never have a display.
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("PYGLET_HEADLESS", "true")
