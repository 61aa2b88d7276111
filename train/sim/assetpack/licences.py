"""Licences of the asset pack: which SPDX ids are allowed and where, and Debian's machine-readable copyright files.

Policy (the project's): an asset whose licence is in :data:`COMMITTABLE` may be shipped or committed with its
credit; one in :data:`SETUP_ONLY` (copyleft: the GPL family, CC-BY-SA) may be used by the set-up step that builds a
pack on a user's machine, and is never committed. Anything else (research-only, non-commercial, unknown) is left
out of a pack. A source may be marked set-up only although its licence would allow more, where its provenance
is not certain enough to commit it (the manifest says why).
"""

from __future__ import annotations

import fnmatch
import re
from dataclasses import dataclass

COMMITTABLE = {
    "CC0-1.0": "https://creativecommons.org/publicdomain/zero/1.0/",
    "LicenseRef-public-domain": "",
    "CC-BY-3.0": "https://creativecommons.org/licenses/by/3.0/",
    "CC-BY-3.0-US": "https://creativecommons.org/licenses/by/3.0/us/",
    "CC-BY-4.0": "https://creativecommons.org/licenses/by/4.0/",
    "MIT": "https://opensource.org/license/mit",
    "BSD-3-Clause": "https://opensource.org/license/bsd-3-clause",
    "Apache-2.0": "https://www.apache.org/licenses/LICENSE-2.0",
}
"""Licences (SPDX ids, with their text's address) whose assets may be committed and shipped, with credit."""

SETUP_ONLY = {
    "GPL-2.0-only": "https://www.gnu.org/licenses/old-licenses/gpl-2.0.html",
    "GPL-2.0-or-later": "https://www.gnu.org/licenses/old-licenses/gpl-2.0.html",
    "GPL-3.0-or-later": "https://www.gnu.org/licenses/gpl-3.0.html",
    "LGPL-3.0-only": "https://www.gnu.org/licenses/lgpl-3.0.html",
    "LGPL-3.0-or-later": "https://www.gnu.org/licenses/lgpl-3.0.html",
    "CC-BY-SA-3.0": "https://creativecommons.org/licenses/by-sa/3.0/",
    "CC-BY-SA-4.0": "https://creativecommons.org/licenses/by-sa/4.0/",
}
"""Copyleft licences: usable by the set-up step that builds a pack, never committed to the repository."""

ALLOWED = {**COMMITTABLE, **SETUP_ONLY}
"""Every licence a pack may hold."""

_SPDX = {
    "cc0": "CC0-1.0", "cc0-1.0": "CC0-1.0", "public-domain": "LicenseRef-public-domain",
    "public domain": "LicenseRef-public-domain", "cc-by-3.0": "CC-BY-3.0", "cc-by-3.0-usa": "CC-BY-3.0-US",
    "cc-by-3.0-us": "CC-BY-3.0-US", "cc-by-4.0": "CC-BY-4.0", "expat": "MIT", "mit": "MIT",
    "bsd-3-clause": "BSD-3-Clause", "apache-2.0": "Apache-2.0", "gpl-2": "GPL-2.0-only", "gpl-2+": "GPL-2.0-or-later",
    "gpl-3+": "GPL-3.0-or-later", "lgplv3": "LGPL-3.0-only", "lgpl-3": "LGPL-3.0-only", "lgpl-3+": "LGPL-3.0-or-later",
    "cc-by-sa-3.0": "CC-BY-SA-3.0", "cc-by-sa-4.0": "CC-BY-SA-4.0",
}


def spdx(name: str) -> str:
    """The SPDX id of a licence name as Debian copyright files and package metadata write it (``GPL-2+``,
    ``CC-BY-3.0-USA``, ``Expat``, ``LGPLv3``, ...); an SPDX id or an unknown name is returned as it is."""
    return _SPDX.get(name.strip().lower(), name.strip())


def committable(licence: str) -> bool:
    """Whether an asset under ``licence`` (an SPDX id) may be committed and shipped."""
    return licence in COMMITTABLE


@dataclass(frozen=True)
class CopyrightParagraph:
    """One ``Files:`` paragraph of a Debian copyright file."""

    files: tuple[str, ...]
    """The glob patterns of ``Files:``."""
    copyright: str
    """The ``Copyright:`` field, its lines joined by ``; `` (may be empty)."""
    licence: str
    """The first line of ``License:``, as written (e.g. ``GPL-2+``)."""


def parse_debian_copyright(text: str) -> list[CopyrightParagraph]:
    """The ``Files:`` paragraphs of a machine-readable Debian copyright file (DEP-5), in file order.

    Args:
        text: the file's text.

    Returns:
        The paragraphs that have both ``Files:`` and ``License:`` (stand-alone licence texts are skipped).
    """
    out = []
    for block in re.split(r"\n\s*\n", text):
        fields: dict[str, list[str]] = {}
        key = None
        for line in block.splitlines():
            if line[:1] in (" ", "\t") and key is not None:
                fields[key].append(line.strip())
            elif ":" in line:
                key, value = line.split(":", 1)
                key = key.strip().lower()
                fields[key] = [value.strip()] if value.strip() else []
        if "files" in fields and "license" in fields and fields["license"]:
            patterns = tuple(p for line in fields["files"] for p in line.split())
            holders = "; ".join(x for x in fields.get("copyright", []) if x)
            out.append(CopyrightParagraph(patterns, holders, fields["license"][0]))
    return out


def lookup_copyright(paragraphs: list[CopyrightParagraph], path: str) -> CopyrightParagraph:
    """The paragraph that covers ``path``: the last one with a matching pattern, as DEP-5 says.

    Args:
        paragraphs: from :func:`parse_debian_copyright`.
        path: a path relative to the source tree's root (e.g. ``base/textures/tex_buildings/carpet020.png``).

    Raises:
        KeyError: no paragraph covers the path.
    """
    for para in reversed(paragraphs):
        if any(fnmatch.fnmatchcase(path, pat) for pat in para.files):
            return para
    raise KeyError(path)
