"""What every fruxel command shares: the runner, argparse types, options made from config dataclasses, ``--grid``.

Every command (``fruxel-render``, ``fruxel-sim``, and the training, evaluation and prediction commands) is a thin
``main(argv=None) -> int`` written the same way::

    import argparse
    from fruxel.cli.common import OneLineParser, config_option, positive_int, run, write_outputs

    def build_parser() -> argparse.ArgumentParser:          # standard library and fruxel's core only: --help is instant
        p = OneLineParser(prog="fruxel-x", description="...")
        config_option(p, XConfig, "steps", type=positive_int)   # --steps, default and help from XConfig.steps
        return p

    def _main(args: argparse.Namespace) -> int | None:      # the work; heavy imports inside
        ...                                                 # raise a FruxelError subclass for bad input
        write_outputs([(args.out, lambda tmp: save(tmp, result))])   # all outputs or none

    def main(argv: list[str] | None = None) -> int:
        return run(_main, build_parser(), argv)

:func:`run` gives every command the same behaviour, so callers and scripts can rely on it:

- exit status 0 on success (or what ``_main`` returns), 2 for bad input, 130 when interrupted (Ctrl-C);
- bad input is one line on stderr, ``PROG: error: MESSAGE``, never a traceback: usage errors from the parser
  (:class:`OneLineParser`), any :class:`fruxel.FruxelError` (every library error derives from it: malformed
  files, impossible grids or cameras, unusable backends, ...; raise :class:`UsageError` for a wrong combination
  of options), and ``OSError`` (a missing file, no permission, a full disk);
- any other exception is a bug in fruxel and keeps its traceback.

Argument vocabulary shared by the commands: :func:`positive_int`, :func:`non_negative_int`,
:func:`unit_fraction`, :func:`positive_float`, :func:`field_of_view` (degrees), :func:`device_name`,
:func:`image_size` (``WxH``), :func:`path_name` (a file or folder name, never empty), and the grid options of
:func:`add_grid_options`: ``--grid N|WxHxD`` (cells) with ``--z-near``, ``--z-far`` and ``--hfov``.

Inputs and outputs are checked before any slow work (loading a model, rendering, simulating):
:func:`check_output_folder` and :func:`check_output_file` find what would stop an output from being written (a file
where a folder must be, a folder where the file must be, no permission), without making anything.
:func:`write_outputs` writes a command's files together (all or none), making their folders and removing what
killed earlier runs left behind.

A closed standard output (``fruxel-train --print-config | head``) ends a command quietly with status 0, as it
ends the standard Unix tools.

Defaults are written once, in the config dataclasses: :func:`config_option` adds an option whose default,
type and help text come from a dataclass field (its docstring), and :func:`config_values` collects the parsed
values of one dataclass's fields for its constructor.

At import time this module loads the standard library and fruxel's numpy-only core, nothing heavier: a
command's ``--help`` stays instant as long as the command imports torch, Warp or pyrender inside ``_main``.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import os
import re
import sys
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from fruxel.errors import FruxelError
from fruxel.grid import FruxelGrid

EXIT_OK = 0
"""Exit status of a command that did what it was asked."""
EXIT_USAGE = 2
"""Exit status for bad input: a usage error, a malformed file, impossible parameters (argparse's own status)."""
EXIT_INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT, as shells report it)."""


# ---------------------------------------------------------------------------------------------------- runner
class UsageError(FruxelError, ValueError):
    """A wrong combination of options, found after parsing (e.g. ``--orbit`` with ``--out x.png``). :func:`run`
    prints it as one line, like the parser's own usage errors."""


def describe_os_error(e: OSError) -> str:
    """One line for an ``OSError``: ``"FILE: what"`` (e.g. ``"out/x.png: Permission denied"``), else its text."""
    what = e.strerror or str(e) or type(e).__name__
    if e.filename is not None:
        target = f"{e.filename} -> {e.filename2}" if e.filename2 is not None else str(e.filename)
        return f"{target}: {what}"
    return what


def one_line(message: object) -> str:
    """``message`` as one line: runs of whitespace, newlines included, become one space."""
    return " ".join(str(message).split())


def run(main_impl: Callable[[argparse.Namespace], int | None], parser: argparse.ArgumentParser,
        argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` with ``parser``, call ``main_impl(args)`` and turn its outcome into an exit status.

    Args:
        main_impl: the command's work. It returns None or 0 for success (or another status to exit with) and
            raises for bad input: any :class:`fruxel.FruxelError` (:class:`UsageError` for options that do not
            go together) or ``OSError``.
        parser: the command's parser; a :class:`OneLineParser` makes usage errors one line too. ``parser.prog``
            starts every error line.
        argv: the arguments, without the program name; None reads ``sys.argv[1:]``.

    Returns:
        The exit status: ``main_impl``'s (0 for None), :data:`EXIT_USAGE` (2) after printing
        ``PROG: error: MESSAGE`` on stderr for a known error, :data:`EXIT_INTERRUPTED` (130) after Ctrl-C, and
        :data:`EXIT_OK` (0), quietly, when standard output is a pipe whose reader has gone (``| head``).

    Raises:
        SystemExit: from the parser, for ``--help`` (status 0) and usage errors (status 2), as argparse does.
        Exception: anything else ``main_impl`` raises: a bug, shown with its traceback.
    """
    prog = parser.prog
    try:
        args = parser.parse_args(argv)
        status = main_impl(args)
        sys.stdout.flush()  # a closed pipe shows here rather than at the interpreter's exit
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (FruxelError, OSError) as e:
        if isinstance(e, BrokenPipeError) and _stdout_closed():
            _silence_stdout()
            return EXIT_OK
        msg = one_line(e) if isinstance(e, FruxelError) else describe_os_error(e)
        hint = " (see --help)" if isinstance(e, UsageError) else ""
        print(f"{prog}: error: {msg}{hint}", file=sys.stderr)
        return EXIT_USAGE
    return EXIT_OK if status is None else int(status)


def _stdout_closed() -> bool:
    """True when standard output is a pipe or socket whose reader has gone (``| head`` that exited).

    Only such a stdout ends a command quietly: a broken pipe anywhere else (a video encoder that died) stays an
    error. Where ``poll`` cannot tell (no ``poll``, no file descriptor), a broken pipe is taken for stdout's: fruxel
    writes its own files through :func:`write_outputs`, which reports their errors itself.
    """
    import select

    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        return True
    if not hasattr(select, "poll"):
        return True
    poller = select.poll()
    poller.register(fd, select.POLLOUT)
    # A pipe without a reader polls as an error (Linux) or as hung up (BSD, macOS).
    return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))


def _silence_stdout() -> None:
    """Point standard output at the null device, so that the interpreter's last flush at exit finds no closed pipe
    (it would print "Exception ignored ... BrokenPipeError")."""
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)
    except (AttributeError, OSError, ValueError):
        pass


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors are one line, ``PROG: error: MESSAGE (see --help)``, exit 2.

    Its sub-command parsers (``add_subparsers``) are made with the same class, so they behave alike.
    """

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see --help)\n")


# ---------------------------------------------------------------------------------------------------- types
def _integer(text: str, low: int, what: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a {what} integer, got {text!r}") from None
    if v < low:
        raise argparse.ArgumentTypeError(f"expected a {what} integer, got {text!r}")
    return v


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    return _integer(text, 1, "positive")


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    return _integer(text, 0, "non-negative")


def _real(text: str, ok: Callable[[float], bool], what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not ok(v):  # NaN fails every comparison, so no check lets it through
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return v


def unit_fraction(text: str) -> float:
    """argparse type: a number in (0, 1], such as an occupancy threshold."""
    return _real(text, lambda v: 0.0 < v <= 1.0, "a number in (0, 1]")


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0, such as frames per second."""
    return _real(text, lambda v: 0.0 < v < float("inf"), "a positive number")


def field_of_view(text: str) -> float:
    """argparse type: a horizontal field of view in degrees, in (0, 180)."""
    return _real(text, lambda v: 0.0 < v < 180.0, "degrees in (0, 180)")


def device_name(text: str) -> str:
    """argparse type: a Warp device, ``cpu``, ``cuda`` or ``cuda:N``."""
    if not re.fullmatch(r"cpu|cuda(:\d+)?", text):
        raise argparse.ArgumentTypeError(f"expected cpu, cuda or cuda:N, got {text!r}")
    return text


def image_size(text: str) -> tuple[int, int]:
    """argparse type: an image size ``WxH`` in pixels, e.g. ``640x480``: ``(width, height)``."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise argparse.ArgumentTypeError(f"expected WxH with positive integers, e.g. 640x480, got {text!r}")
    return int(m.group(1)), int(m.group(2))


def path_name(text: str) -> Path:
    """argparse type: a file or folder name. An empty or blank one is refused: ``Path("")`` is the current folder,
    which ``--out ""`` (an unset shell variable) surely did not mean."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a file or folder name, got {text!r}")
    return Path(text)


def grid_size(text: str) -> tuple[int, int, int]:
    """argparse type: a grid size in cells, ``N`` (N x N x N) or ``WxHxD``: ``(width, height, depth)``."""
    parts = text.strip().lower().split("x")
    try:
        values = [int(p) for p in parts]
    except ValueError:
        values = []
    if len(values) == 1:
        values *= 3
    if len(values) != 3 or min(values) < 1:
        hint = ""
        if len(re.split(r"[,\s]+", text.strip())) == 6:
            # The older W,H,D,z_near,z_far,hfov form of fruxel-render.
            hint = "; the depth range and field of view are --z-near, --z-far and --hfov"
        raise argparse.ArgumentTypeError(f"expected N or WxHxD with positive integers, e.g. 128 or 160x120x128, "
                                         f"got {text!r}{hint}")
    return values[0], values[1], values[2]


# ---------------------------------------------------------------------------------------------------- dataclasses
def _tidy(doc: str) -> str:
    """A field docstring as plain help text: reST roles and literals unwrapped, whitespace collapsed, ``%``
    escaped for argparse."""
    # Sphinx semantics: :role:`~a.b.c` shows "c", :role:`a.b.c` shows it whole.
    text = re.sub(r":[a-z]+:`(~?)([^`<]*?)\s*(?:<[^>]*>)?`",
                  lambda m: m.group(2).split(".")[-1] if m.group(1) else m.group(2), doc)
    text = text.replace("``", "")
    return one_line(text).replace("%", "%%")


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstrings of a dataclass's fields (the string literal written under each field), by field name.

    Read from the class's source with :mod:`ast`; fields without one are left out (inherited fields are not
    read).
    """
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    body = next(n for n in ast.parse(source).body if isinstance(n, ast.ClassDef)).body
    docs = {}
    for node, nxt in zip(body, body[1:], strict=False):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str)):
            docs[node.target.id] = inspect.cleandoc(nxt.value.value)
    return docs


def _field(config: Any, name: str) -> dataclasses.Field[Any]:
    cls = config if isinstance(config, type) else type(config)
    for f in dataclasses.fields(cls):
        if f.name == name:
            return f
    raise AttributeError(f"{cls.__name__} has no field {name!r}")


def field_default(config: Any, name: str) -> Any:
    """The value of field ``name``: the instance's when ``config`` is a dataclass instance, else the class's
    default (made by its default factory where it has one)."""
    if not isinstance(config, type):
        return getattr(config, name)
    f = _field(config, name)
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    raise AttributeError(f"{config.__name__}.{name} has no default")


_SCALARS: dict[str, Callable[[str], Any]] = {"int": int, "float": float, "str": str}


def config_option(parser: Any, config: Any, name: str, *flags: str, **kwargs: Any) -> argparse.Action:
    """Add the option for field ``name`` of a config dataclass: its default, type and help come from the field.

    Args:
        parser: an ``ArgumentParser`` or argument group.
        config: the dataclass, or an instance of it whose values are the defaults (a command that wants another
            default than the class's passes an instance, e.g. ``ImageConfig(size=256)``).
        name: the field; it is also the option's ``dest``, which :func:`config_values` reads.
        flags: the option strings; default ``--NAME`` with ``_`` as ``-`` (``--no-NAME`` for a bool field whose
            default is True).
        kwargs: anything else for ``add_argument`` (``type``, ``choices``, ``metavar``), overriding what is
            derived: the type from the annotation (``int``, ``float``, ``str``, optionally ``| None``; a bool
            field becomes a flag that stores the opposite of its default); the help from the field's docstring
            followed by the default.

    Returns:
        The argparse action.
    """
    cls = config if isinstance(config, type) else type(config)
    default = field_default(config, name)
    annotation = str(_field(cls, name).type).replace(" ", "")
    kind = annotation.removesuffix("|None")
    option = name.replace("_", "-")
    kwargs.setdefault("dest", name)
    kwargs.setdefault("default", default)
    help_text = _tidy(field_docs(cls).get(name, ""))
    if kind == "bool" and "action" not in kwargs and "type" not in kwargs:
        flags = flags or ((f"--no-{option}",) if default else (f"--{option}",))
        kwargs.setdefault("action", "store_false" if default else "store_true")
        # The docstring describes the setting, which the flag turns on, or (on by default) off: a --no-... flag
        # says so first, lest "--no-legend  Draw the class legend" read as what the flag does.
        if default:
            help_text = f"turn off (on by default): {_lower_first(help_text)}"
        else:
            help_text += " (default: off)"
    else:
        flags = flags or (f"--{option}",)
        if "type" not in kwargs and "choices" not in kwargs and kind in _SCALARS:
            kwargs["type"] = _SCALARS[kind]
        if kwargs["default"] is not None:
            help_text += f" (default: {kwargs['default']})"
    kwargs.setdefault("help", help_text)
    return parser.add_argument(*flags, **kwargs)


def _lower_first(text: str) -> str:
    """``text`` with its first letter in lower case, unless its first word is an acronym or a name (``SSZ``)."""
    word = text.split(" ", 1)[0]
    return text[:1].lower() + text[1:] if word[:1].isupper() and word[1:2].islower() else text


def config_values(args: argparse.Namespace, cls: type, **given: Any) -> dict[str, Any]:
    """The parsed values of ``cls``'s fields that have options (``dest`` = field name), plus ``given``: keyword
    arguments for ``cls(...)``."""
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)}
    values.update(given)
    return values


# ---------------------------------------------------------------------------------------------------- grid
def add_grid_options(parser: Any, default: FruxelGrid, *, size_default: bool = True, what: str = "",
                     hfov_help: str = "") -> None:
    """Add ``--grid N|WxHxD``, ``--z-near``, ``--z-far`` and ``--hfov``: a :class:`fruxel.FruxelGrid`.

    Args:
        parser: an ``ArgumentParser`` or argument group.
        default: the grid whose values are the defaults (a config dataclass's default grid); help texts come
            from :class:`fruxel.FruxelGrid`'s field docstrings.
        size_default: False when the grid has no default size (``--grid`` given or no grid at all, see
            :func:`grid_from_args`).
        what: words appended to ``--grid``'s help, e.g. ``"of a bare logits tensor"``.
        hfov_help: words appended to ``--hfov``'s help (another use of the option, e.g. a photo's field of view).
    """
    docs = field_docs(FruxelGrid)
    size = f"{default.width}x{default.height}x{default.depth}"
    parser.add_argument("--grid", type=grid_size, default=None, metavar="N|WxHxD",
                        help=f"grid size in cells, N for N x N x N or W x H x D{' ' + what if what else ''}"
                        + (f" (default: {size})" if size_default else ""))
    for name, metavar in (("z_near", "M"), ("z_far", "M"), ("hfov", "DEG")):
        parser.add_argument(f"--{name.replace('_', '-')}", dest=name, type=float, default=None, metavar=metavar,
                            help=f"grid: {_tidy(docs.get(name, name))} (default: {getattr(default, name):g})"
                            + (f"; {hfov_help}" if name == "hfov" and hfov_help else ""))


def grid_options_given(args: argparse.Namespace) -> list[str]:
    """The grid options given on the command line (of those :func:`add_grid_options` adds)."""
    names = {"grid": "--grid", "z_near": "--z-near", "z_far": "--z-far", "hfov": "--hfov"}
    return [flag for dest, flag in names.items() if getattr(args, dest, None) is not None]


def grid_from_args(args: argparse.Namespace, default: FruxelGrid, *, size_default: bool = True
                   ) -> FruxelGrid | None:
    """The grid of :func:`add_grid_options`: each value given, else ``default``'s.

    Returns:
        The grid; None when ``size_default`` is False and no grid option was given.

    Raises:
        UsageError: ``--z-near``, ``--z-far`` or ``--hfov`` without ``--grid`` when the size has no default.
        GridError: impossible values (``z_far <= z_near``, ...).
    """
    if args.grid is None and not size_default:
        given = grid_options_given(args)
        if given:
            raise UsageError(f"{', '.join(given)} describe the grid of --grid; give --grid WxHxD as well")
        return None
    w, h, d = args.grid if args.grid is not None else (default.width, default.height, default.depth)
    z = {n: getattr(args, n) if getattr(args, n) is not None else getattr(default, n)
         for n in ("z_near", "z_far", "hfov")}
    return FruxelGrid(width=w, height=h, depth=d, **z)


# ---------------------------------------------------------------------------------------------------- outputs
class OutputError(FruxelError, OSError):
    """An output file that could not be written; the message names the file (never a temporary name)."""


def _existing_ancestor(path: Path) -> Path:
    """``path`` itself if it exists, else its nearest existing parent (``.`` for a relative name)."""
    for p in (path, *path.parents):
        if p.exists():
            return p
    return Path(".")


def check_output_folder(folder: str | Path, flag: str) -> None:
    """Check, before any slow work, that files can be written into ``folder`` (made where missing): it is a folder
    or can be made as one, and the folder that holds it lets this user write. Nothing is made.

    Args:
        folder: the output folder.
        flag: the option that names it (``"--out"``), for the message.

    Raises:
        OutputError: a file where the folder (or one of its parents) must be, or a folder this user may not write
            in; the message names ``flag`` and the folder.
    """
    folder = Path(folder)
    base = _existing_ancestor(folder)
    if not base.is_dir():
        if base == folder:
            raise OutputError(f"{flag} {folder} is a file, not a folder")
        raise OutputError(f"cannot write into {flag} {folder}: {base} is a file, not a folder")
    if not os.access(base, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write into {flag} {folder}: {base} is not writable (permission denied)")


def check_output_file(target: str | Path, flag: str) -> None:
    """Check, before any slow work, that the file ``target`` can be written (its folder made where missing): it is
    not a folder, and :func:`check_output_folder` passes for its folder. Nothing is made.

    Raises:
        OutputError: a folder where the file must be, or an unusable folder (:func:`check_output_folder`); the
            message names ``flag`` and the file.
    """
    target = Path(target)
    if target.is_dir():
        raise OutputError(f"cannot write {flag} {target}: it is a folder")
    base = _existing_ancestor(target.parent)
    if not base.is_dir():
        raise OutputError(f"cannot write {flag} {target}: {base} is a file, not a folder")
    # Writes are atomic (a temporary file renamed over the target): the folder's permission is what counts.
    if not os.access(base, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write {flag} {target}: {base} is not writable (permission denied)")


def _make_folder(folder: Path, target: Path, made: list[Path]) -> None:
    """Make ``folder`` and its missing parents, recording the topmost one made in ``made``."""
    missing = [f for f in (folder, *folder.parents) if not f.exists()]
    if not missing:
        if not folder.is_dir():
            raise OutputError(f"cannot write {target}: {folder} is not a folder")
        return
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot write {target}: cannot make the folder {folder} ({e.strerror or e})") from None
    made.append(missing[-1])


def _remove_made_folders(made: list[Path], targets: Sequence[Path]) -> None:
    """Remove the folders :func:`_make_folder` made, as far as they are empty again."""
    for target in targets:
        for folder in (target.parent, *target.parent.parents):
            if not any(folder == m or m in folder.parents for m in made):
                break
            try:
                folder.rmdir()
            except OSError:
                break


def write_outputs(outputs: Sequence[tuple[str | Path, Callable[[Path], None]]]) -> list[Path]:
    """Write a command's output files together: all of them or, when anything fails, none.

    For every ``(target, write)``: the target's folder is made where missing, temporary files that killed
    earlier runs left beside the target are removed (:func:`fruxel.io.remove_stale_temporaries`), and
    ``write(tmp)`` writes the file to a temporary name beside it with the target's suffix. Once every file is
    written, they replace their targets (:func:`fruxel.io.atomic_files`). When any step fails, no target
    changes, the temporary files are removed, and so are the folders this call made (where empty again).

    Args:
        outputs: the targets and their writers; a writer writes its file to the path it is given (the format
            follows the target's suffix, which the temporary name ends with too).

    Returns:
        The targets, in order.

    Raises:
        OutputError: a target that cannot be written (no permission, a file where a folder should be, a full
            disk); the message names the target.
    """
    from fruxel.io import atomic_files, remove_stale_temporaries

    targets = [Path(t) for t, _ in outputs]
    made: list[Path] = []
    try:
        for target in targets:
            _make_folder(target.parent, target, made)
            remove_stale_temporaries(target)
        try:
            with atomic_files() as files:
                for target, (_, write) in zip(targets, outputs, strict=True):
                    try:
                        write(files.path(target))
                    except OSError as e:
                        raise OutputError(f"cannot write {target}: {e.strerror or one_line(e)}") from None
        except OutputError:
            raise
        except OSError as e:
            # A sync or rename at the end: os.replace names the target second.
            name = e.filename2 if e.filename2 is not None else ", ".join(map(str, targets))
            raise OutputError(f"cannot write {name}: {e.strerror or one_line(e)}") from None
    except BaseException:
        _remove_made_folders(made, targets)
        raise
    return targets


# ---------------------------------------------------------------------------------------------------- photos
MIN_PHOTO_SIDE = 16
"""Fewest pixels a photo may have on its shorter side: SSZ reads a view of the room, and a thumbnail of a few
pixels (a 1 x 1 picture, an icon) holds none."""
MAX_PHOTO_ASPECT = 8.0
"""Most times a photo may be wider than high, or higher than wide. A camera's view, panoramas included, is within
4 : 1; a 4000 x 50 strip is not a view of a room: cropped to the model's aspect (``--fit crop``) it would keep a
sliver of 1 %, padded (``--fit pad``) a line in grey."""


class PhotoError(FruxelError, ValueError):
    """A photo a command cannot read or use; the message names the file."""


def check_photo(path: str | Path) -> tuple[int, int]:
    """Check a photo before any slow work, from its header alone (nothing is decoded): it exists, Pillow knows its
    format, its pixels have a known range (not 32-bit integers), and its size is one a camera gives: at least
    :data:`MIN_PHOTO_SIDE` pixels on the shorter side, at most :data:`MAX_PHOTO_ASPECT` times as long as it is wide.
    Damaged pixel data and float pixels out of [0, 1] show when the photo is decoded
    (:func:`fruxel.train.predict.load_image`), which names the file too.

    Returns:
        ``(width, height)`` in pixels, as stored (before any EXIF rotation).

    Raises:
        PhotoError: a missing file, a folder, a file that is no image Pillow reads, 32-bit integer pixels, or a
            size out of those limits; the message names the file.
    """
    from PIL import Image, UnidentifiedImageError

    p = os.fsdecode(path)
    if not os.path.exists(p):
        raise PhotoError(f"{p}: no such file")
    if not os.path.isfile(p):
        raise PhotoError(f"{p}: not a regular file")
    try:
        with Image.open(p) as im:
            (w, h), mode, kind = im.size, im.mode, im.format
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as e:
        raise PhotoError(f"{p}: not a readable image ({type(e).__name__}: {one_line(e)})") from None
    if mode == "I" and kind != "PNG":  # as load_image refuses it (a PNG's "I" is 16-bit grey in old Pillows)
        raise PhotoError(f"{p}: 32-bit integer pixels have no range to scale them by; save the photo with 8 or 16 "
                         "bits a channel")
    if min(w, h) < MIN_PHOTO_SIDE:
        raise PhotoError(f"{p}: {w}x{h} pixels is too small to show a room (fruxel reads photos of at least "
                         f"{MIN_PHOTO_SIDE} pixels a side)")
    if max(w, h) > MAX_PHOTO_ASPECT * min(w, h):
        raise PhotoError(f"{p}: {w}x{h} pixels is a strip, not a camera's view (fruxel reads photos at most "
                         f"{MAX_PHOTO_ASPECT:g} times as long as wide)")
    return w, h


# ---------------------------------------------------------------------------------------------------- asset pack
def add_assets_option(parser: Any, what: str = "the furnished rooms") -> None:
    """Add ``--assets DIR``: the asset pack folder (``SimConfig.assets``; None when not given)."""
    parser.add_argument("--assets", default=None, type=path_name, metavar="DIR",
                        help=f"the asset pack folder of {what} (default: $FRUXEL_ASSETS, else the repository's "
                        "assets/pack, which `make assets` builds)")


def check_asset_pack(config: Any) -> None:
    """:func:`fruxel.train.sim.rooms.check_pack` for a command, whose ``config.assets`` comes from ``--assets``.

    Raises:
        ConfigError: no pack in the folder (one line naming it, where it came from and ``make assets``).
    """
    from fruxel.train.sim.rooms.library import check_pack

    check_pack(config, option="--assets")


# ---------------------------------------------------------------------------------------------------- test sets
def add_test_set_options(parser: Any) -> None:
    """Add ``--test-set NAME`` (:data:`fruxel.train.sim.testsets.TEST_SETS`; None when not given) and ``--assets
    DIR`` (:func:`add_assets_option`): streamed samples of a held-out test set."""
    from fruxel.train.sim.testsets import TEST_SETS

    parser.add_argument("--test-set", default=None, choices=tuple(TEST_SETS), metavar="NAME",
                        help="stream the samples of a held-out test set (default: any-camera for a model with the "
                        "classes ceiling and object, else the flat world from the robot's mount): "
                        + "; ".join(f"{s.name}: {s.description}" for s in TEST_SETS.values())
                        + " (the first two need a model with the classes ceiling and object)")
    add_assets_option(parser, "the room-world test sets")


def check_test_set_options(args: argparse.Namespace) -> None:
    """Refuse ``--test-set`` with ``--data`` and ``--assets`` without ``--test-set``, before any work.

    Raises:
        UsageError: the options that do not go together, named.
    """
    if args.test_set is not None and args.data is not None:
        raise UsageError(f"--test-set {args.test_set} streams the test set's samples; a data set (--data) has its own; "
                         "give one of them")
    if args.assets is not None and args.test_set is None:
        raise UsageError("--assets names the asset pack of a --test-set's furnished rooms; give --test-set NAME")


def streamed_source(args: argparse.Namespace, model: Any, **fields: Any) -> Any:
    """The streamed :class:`fruxel.train.samples.SampleSource` of ``--seed``, ``--test-set`` (by default the one
    the model's classes call for, :func:`fruxel.train.sim.testsets.default_test_set`) and ``--assets``, with
    ``fields`` more, checked against the model (:func:`check_stream`)."""
    from fruxel.train.samples import SampleSource
    from fruxel.train.sim.testsets import default_test_set

    test_set = args.test_set or default_test_set(model.classes)
    source = SampleSource(seed=args.seed or 0, assets=str(args.assets or ""), test_set=test_set, **fields)
    check_stream(source, model)
    return source


def data_source(root: str | Path, model: Any) -> Any:
    """The :class:`fruxel.train.samples.SampleSource` of ``--data DIR``, checked against the model: a data folder of
    labelled photos when ``DIR`` holds a ``dataset.json`` (:mod:`fruxel.train.folder`), else a data set of shards.

    Raises:
        DataError: see :func:`fruxel.train.samples.check_data_set` and
            :func:`~fruxel.train.samples.check_folder_set` (one line naming the file).
    """
    from fruxel.train.folder import is_folder_set
    from fruxel.train.samples import SampleSource, check_data_set, check_folder_set

    if is_folder_set(root):
        check_folder_set(str(root), model)
        return SampleSource("folder", str(root))
    return SampleSource("shards", str(root), check_data_set(str(root), model).seed)


def check_stream(source: Any, model: Any) -> None:
    """Check, before any slow work, that a streamed sample source fits a model: a test set of the room world needs
    the model's classes to include the ones that world labels, and its asset pack (:func:`check_asset_pack`).

    Args:
        source: the :class:`fruxel.train.samples.SampleSource` (shards pass unchecked).
        model: the model's config (grid, image size, classes).

    Raises:
        UsageError: a room-world test set for a model without its classes (one line naming them).
        ConfigError: no asset pack there, or another config the simulator refuses.
    """
    if source.source != "stream":
        return
    from fruxel.train.samples import sim_config
    from fruxel.train.sim.rooms import CLASS_NAMES
    from fruxel.train.sim.testsets import TEST_SETS

    if source.test_set and TEST_SETS[source.test_set].world == "home":
        missing = [n for n in CLASS_NAMES if n not in model.classes.names]
        if missing:
            raise UsageError(f"--test-set {source.test_set} is a set of furnished rooms, labelled with "
                             f"{', '.join(CLASS_NAMES)}; the model's classes lack {', '.join(missing)} (it learnt "
                             "another world; --test-set robot fits it)")
    check_asset_pack(sim_config(model, source, (("test", 1),)))


# ---------------------------------------------------------------------------------------------------- models
def add_model_options(parser: Any) -> None:
    """Add ``--checkpoint FILE`` and ``--device cpu|cuda[:N]``: the trained SSZ model a command runs, and where.

    ``--checkpoint`` is a shipped ``.safetensors`` file, a training checkpoint ``.pt`` or a shipped model's name
    (:func:`fruxel.train.model_files.load_model` reads each); None (not given) means the model shipped with fruxel
    as the default (``ssz64-any``). ``--device`` is None when not given: :func:`torch_device` then picks CUDA when
    present.
    """
    parser.add_argument("--checkpoint", default=None, metavar="FILE",
                        help="the model: a shipped .safetensors file, a training checkpoint .pt, or a model shipped "
                        "with fruxel by name: ssz64-any (the default: 64^3 cells, any camera; reads --pitch/--roll/"
                        "--height where a command takes them), ssz64 (64^3 cells, the robot's mount) or ssz128 "
                        "(ssz64 at 128^3 from 512x512)")
    parser.add_argument("--device", type=device_name, default=None, metavar="cpu|cuda[:N]",
                        help="where the model runs (default: cuda when present, else cpu)")


def torch_device(name: str | None) -> Any:
    """The ``torch.device`` of ``--device`` (:func:`add_model_options`): CUDA when present if None.

    Raises:
        UsageError: a CUDA device asked for on a machine without one (or without that one).
    """
    import torch

    if name is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise UsageError(f"--device {name}: no CUDA device here")
        index = int(name.partition(":")[2] or 0)
        if index >= torch.cuda.device_count():
            raise UsageError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA devices, "
                             f"cuda:0 to cuda:{torch.cuda.device_count() - 1}")
    return torch.device(name)


# ---------------------------------------------------------------------------------------------------- photo cameras
def angle(text: str) -> float:
    """argparse type: a pitch or roll in degrees, in (-90, 90)."""
    return _real(text, lambda v: -90.0 < v < 90.0, "degrees in (-90, 90)")


def camera_height(text: str) -> float:
    """argparse type: a camera's height above the floor in metres, in (0, 10]."""
    return _real(text, lambda v: 0.0 < v <= 10.0, "metres in (0, 10]")


def intrinsics(text: str) -> tuple[float, float, float, float]:
    """argparse type: ``fx,fy,cx,cy`` in pixels of the photo, focal lengths > 0."""
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 4 or not all(v == v and abs(v) != float("inf") for v in values) or min(values[:2]) <= 0:
        raise argparse.ArgumentTypeError(f"expected fx,fy,cx,cy (pixels, fx and fy > 0), got {text!r}")
    return values  # type: ignore[return-value]


def add_camera_options(parser: Any, hfov: bool = True) -> None:
    """Add what is known of a photo's camera: ``--pitch``, ``--roll``, ``--height`` (for a model that reads the
    camera: :class:`fruxel.train.predict.CameraPrior`) and ``--intrinsics fx,fy,cx,cy``, with ``--hfov DEG`` too
    unless the command has its own (``hfov=False``). :func:`camera_prior` and :func:`photo_view` read them."""
    parser.add_argument("--pitch", type=angle, default=None, metavar="DEG",
                        help="the camera's pitch in degrees, positive looking down (default unknown; a model that "
                        "reads the camera then knows gravity, with --roll 0 unless given)")
    parser.add_argument("--roll", type=angle, default=None, metavar="DEG",
                        help="the camera's roll in degrees, positive clockwise as seen from behind it (default 0 "
                        "with --pitch, else unknown)")
    parser.add_argument("--height", type=camera_height, default=None, metavar="M",
                        help="the camera's height above the floor in metres (default unknown; needs --pitch)")
    if hfov:
        parser.add_argument("--hfov", type=field_of_view, default=None, metavar="DEG",
                            help="the photos' horizontal field of view in degrees (default: from the photo's EXIF "
                            "35 mm focal length, else the model grid's own); a wider photo is cropped to the grid's "
                            "view, a narrower one padded")
    parser.add_argument("--intrinsics", type=intrinsics, default=None, metavar="FX,FY,CX,CY",
                        help="the photos' pinhole intrinsics in pixels (instead of --hfov): the photo is cropped "
                        "about the principal point to square pixels")


def camera_prior(args: argparse.Namespace) -> Any:
    """The :class:`fruxel.train.predict.CameraPrior` of ``--pitch``, ``--roll`` and ``--height``, checked.

    Raises:
        UsageError: ``--intrinsics`` with ``--hfov``; ``--height`` without ``--pitch`` or ``--roll``.
    """
    if getattr(args, "intrinsics", None) is not None and getattr(args, "hfov", None) is not None:
        raise UsageError("--intrinsics and --hfov both give the field of view; give one")
    if args.height is not None and args.pitch is None and args.roll is None:
        raise UsageError(f"--height {args.height:g} needs --pitch: a model reads the height along gravity")
    from fruxel.train.predict import CameraPrior

    return CameraPrior(pitch=args.pitch, roll=args.roll, height=args.height)


def note_unread_camera(args: argparse.Namespace, config: Any, prog: str) -> None:
    """One line on stderr when ``--pitch``, ``--roll`` or ``--height`` were given for a model that reads no camera
    (``config.reads_camera`` False, e.g. the shipped ``ssz64``): they change nothing, and a user should know."""
    given = [f"--{name}" for name in ("pitch", "roll", "height") if getattr(args, name, None) is not None]
    if given and not config.reads_camera:
        print(f"{prog}: note: this model reads no camera; {', '.join(given)} change nothing", file=sys.stderr)


def photo_view(path: str | Path, image: Any, args: argparse.Namespace, prog: str, default_hfov: float) -> Any:
    """A photo and its horizontal field of view as the model's framing takes them: ``--intrinsics`` (the photo
    cropped about the principal point), else ``--hfov``, else the photo's EXIF 35 mm-equivalent focal length
    (:func:`fruxel.train.predict.exif_focal_35mm`: one warning line on stderr when it is absurd), else None (the
    model grid's own, ``default_hfov``).

    Args:
        path: the photo's file.
        image: its ``(h, w, 3)`` uint8 RGB (upright).
        args: the parsed options (:func:`add_camera_options`).
        prog: the command's name, for the warning.
        default_hfov: the field of view used when nothing gives one, degrees (named in the warning).

    Returns:
        ``(image (h', w', 3) uint8, hfov degrees or None)``.

    Raises:
        UsageError: ``--intrinsics`` whose principal point lies outside the photo.
    """
    from fruxel.train.predict import centre_intrinsics, exif_focal_35mm, hfov_from_focal_35mm

    if getattr(args, "intrinsics", None) is not None:
        try:
            return centre_intrinsics(image, args.intrinsics)
        except ValueError as e:
            raise UsageError(f"--intrinsics for {path}: {e}") from None
    if args.hfov is not None:
        return image, args.hfov
    focal, why = exif_focal_35mm(path)
    if why is not None:
        print(f"{prog}: warning: {path}: {why}; using {default_hfov:g} degrees across (give --hfov)",
              file=sys.stderr)
    if focal is None:
        return image, None
    return image, hfov_from_focal_35mm(focal, image.shape[1], image.shape[0])
