"""fruxel.cli: the application layer, fruxel's command-line programs (conventions section 6).

* :mod:`fruxel.cli.common` — what every command shares: the runner (errors and exit codes), argparse types,
  options made from config dataclasses, the ``--grid`` options.
* :mod:`fruxel.cli.render` — ``fruxel-render``: show a model or logits as a mesh or a ray-cast image, Table 1.
* :mod:`fruxel.cli.sim` — ``fruxel-sim``: simulated data sets and previews.

Each command is a thin ``main(argv=None) -> int`` listed in ``[project.scripts]``. This layer may import every
library layer (fruxel, kernels, render, train); none of them imports it.
"""
