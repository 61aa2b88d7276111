"""The common base of the errors fruxel raises for bad input, so that a program can tell them from bugs."""

from __future__ import annotations


class FruxelError(Exception):
    """Base of every error fruxel raises for input it cannot use: a malformed file, impossible parameters, an
    unusable backend, a volume of the wrong shape. Its message is one line that names the file or argument and
    the problem, fit to show a user as it is.

    Each concrete error also derives from the built-in type it has always been (``ValueError`` for most,
    ``RuntimeError`` for an unavailable backend), so existing ``except ValueError`` code keeps working. The
    command-line programs turn a ``FruxelError`` into one ``PROG: error: MESSAGE`` line and exit status 2
    (:func:`fruxel.cli.common.run`); any other exception is a bug and keeps its traceback.
    """


class ConfigError(FruxelError, ValueError):
    """An impossible or malformed setting of any fruxel config (experiment, simulator, inference rules): the message
    names the key (``model.levels``, ``room.size``...) and what is wrong with it. The one config error of the
    project: every config dataclass raises it from its own validation."""
