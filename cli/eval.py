"""``fruxel-eval``: the metrics of conventions section 9 for a trained SSZ model, against the two baselines.

Usage::

    fruxel-eval [--checkpoint FILE] [--data DIR [--split test] | --test-set NAME [--assets DIR]] [--samples N]
                [--seed S] [--no-augment] [--prior-samples N] [--out DIR] [--batch B] [--workers K]
                [--device cpu|cuda[:N]] [--backend NAME] [--examples N]
                [--camera-known gravity,height|gravity|none ...] [--by-camera] [-q]

The model (``--checkpoint``) is a shipped ``.safetensors`` file, a training checkpoint ``.pt`` or a shipped model's name
(``ssz64``, ``ssz128``, ``ssz64-any``); by default the model shipped with fruxel as the default (``ssz64-any``). Samples
are the first N of a data set's split (``--data DIR --split test``, shards from ``fruxel-sim generate``, whose grid,
image size and classes must be the model's; N defaults to the whole split) or N samples of the simulator's test split
streamed for the model's grid and image size (default 256, ``--seed``): by default the ``any-camera`` test set for a
model that labels the furnished rooms' classes, else the flat world from the robot's mount (the samples of earlier
reports, as ``--test-set robot`` gives them) (:func:`fruxel.train.sim.testsets.default_test_set`); with ``--test-set
NAME`` those of a held-out test set (:data:`fruxel.train.sim.testsets.TEST_SETS`: ``any-camera`` and
``any-camera-test-assets``, furnished rooms from any camera with training or held-out assets, from the asset pack
``--assets`` names; ``robot``, the robot's mount in the flat world). A room-world set needs a model whose classes
include ``ceiling`` and ``object``. The same samples are predicted by

* the model (argmax of its logits),
* the **per-cell prior**: each cell's most frequent label over ``--prior-samples`` samples of the training split
  of the same source (``0`` leaves it out). Counting them takes minutes on a CPU (the streamed samples are
  simulated), so the prior is kept in a cache (:func:`prior_cache_path`, a fruxel model file under
  ``$FRUXEL_CACHE_DIR``, default ``~/.cache/fruxel``) keyed by everything that makes it: the source (the
  simulator's settings and seed with the asset pack's manifest, or the data set's manifest), the number of
  samples, the model's grid and classes, and fruxel's own code; a later evaluation of the same source reads it back,
* the **visible-surface oracle**: the ground truth's own-view shell alone (a perfect depth and segmentation
  network that completes nothing),

and every metric is counted over all of them together: IoU per class, mIoU over the classes present, completion
IoU, own- and novel-view first-hit accuracy and novel-view depth error.

Outputs, written together into ``--out`` (default ``out/``): ``report.md`` (tables, the command line, model file,
samples, data source, test set and machine), ``report.json`` (the same numbers with the confusion matrices and counts
behind them) and ``examples.png`` (image | truth and prediction from the grid's own camera | truth and prediction
from a novel pose; not written with ``--examples 0``). With ``--by-camera`` the model's mIoU and own-view
accuracy are also counted per bin of camera height (0.3 to 1.9 m in 0.2 m bins) and pitch (-20 to 40 degrees in 10
degree bins) by the samples' recorded cameras (:mod:`fruxel.train.eval.by_camera`): the ``by_camera`` section of
``report.json``, a table per axis in ``report.md`` and ``by_camera.png``. A model that reads the camera is told what
``--camera-known`` says of each sample's camera (default ``gravity,height``); given several times, the model is
evaluated under each setting on the same samples (results ``model`` for the first, ``model@none``,
``model@gravity`` for the others) and the chart draws a curve per setting. Errors are one line
``fruxel-eval: error: ...`` with exit status 2 (:func:`fruxel.cli.common.run`).

Streamed samples are kept in the same cache (``samples/`` beside the priors' ``prior/``,
:mod:`fruxel.train.eval.sample_cache`), keyed likewise, so a second evaluation of the same samples (another
checkpoint of a run, another arm of an experiment) simulates nothing.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shlex
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from .common import (
    OneLineParser,
    UsageError,
    add_model_options,
    add_test_set_options,
    check_output_folder,
    check_test_set_options,
    data_source,
    non_negative_int,
    path_name,
    positive_int,
    run,
    streamed_source,
    torch_device,
    write_outputs,
)

PROG = "fruxel-eval"
DEFAULT_OUT = Path("out")
"""Output folder when ``--out`` is not given."""
STREAM_SAMPLES = 256
"""Streamed test samples when ``--samples`` is not given."""
PRIOR_SAMPLES = 1024
"""Training samples of the per-cell prior when ``--prior-samples`` is not given."""
OUTPUTS = ("report.md", "report.json", "examples.png")
"""Files written into ``--out`` (and :data:`CHART` with ``--by-camera``)."""
CHART = "by_camera.png"
"""The chart of ``--by-camera``, beside the report."""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``fruxel-eval`` (standard library only: ``--help`` is instant)."""
    p = OneLineParser(
        prog=PROG,
        description="Evaluate an SSZ model on a data set split or on streamed simulator samples: IoU per class, "
        "mIoU, completion IoU, own- and novel-view first-hit accuracy and depth error, beside two baselines on the "
        "same samples: the per-cell prior (each cell's most frequent training label) and the visible-surface "
        "oracle (the true own-view surface alone). Writes report.md, report.json and examples.png.",
    )
    add_model_options(p)
    p.add_argument("--data", type=path_name, default=None, metavar="DIR",
                   help="a data set folder made by fruxel-sim generate, or a data folder of labelled photos (with a "
                   "dataset.json: docs/your-data.md) (default: stream samples from the simulator)")
    p.add_argument("--split", default="test", metavar="NAME", help="the data set's split to evaluate on (default test)")
    add_test_set_options(p)
    p.add_argument("--samples", type=positive_int, default=None, metavar="N",
                   help=f"evaluate on the first N samples (default: the whole split of --data, else {STREAM_SAMPLES} "
                   "streamed test samples, kept in the cache for the next evaluation of the same samples)")
    p.add_argument("--seed", type=non_negative_int, default=None, metavar="S",
                   help="base seed of the streamed samples (default 0; a data set has its own)")
    p.add_argument("--no-augment", dest="augment", action="store_false",
                   help="stream images without appearance augmentation (default: augmented, as in training)")
    p.add_argument("--prior-samples", type=non_negative_int, default=PRIOR_SAMPLES, metavar="N",
                   help="training samples counted for the per-cell prior, from the train split of the same source "
                   f"(0 leaves the prior out; default {PRIOR_SAMPLES}, at most the data set's train split); kept in "
                   f"a cache for later evaluations ($FRUXEL_CACHE_DIR, default ~/.cache/fruxel)")
    p.add_argument("--out", type=path_name, default=DEFAULT_OUT, metavar="DIR",
                   help=f"output folder (default {DEFAULT_OUT}/): {', '.join(OUTPUTS)}")
    p.add_argument("--batch", type=positive_int, default=8, metavar="B", help="samples per batch (default 8)")
    p.add_argument("--workers", type=non_negative_int, default=0, metavar="K",
                   help="worker processes that make or read the samples (default 0: this process)")
    p.add_argument("--backend", default=None, metavar="NAME",
                   help="kernel backend of the views and the oracle: warp, opencl, warp-cpu, warp-cuda (default: the "
                   "best available)")
    p.add_argument("--examples", type=non_negative_int, default=4, metavar="N",
                   help="samples shown in examples.png (default 4; 0: no picture)")
    p.add_argument("--camera-known", type=camera_pieces, action="append", default=None,
                   metavar="gravity,height|gravity|none",
                   help="for a model that reads the camera: what it is told of each test sample's recorded camera "
                   "(default gravity,height: pose given, as the test set records it; none: pose unknown); given "
                   "again, the model is also evaluated under that setting on the same samples (e.g. --camera-known "
                   "gravity,height --camera-known none); a model that reads no camera ignores one setting")
    p.add_argument("--by-camera", action="store_true",
                   help=f"also count mIoU and own-view accuracy per bin of camera height ({_edges_text('height')}) "
                   f"and pitch ({_edges_text('pitch')}), into report.json and {CHART}")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars or summary")
    return p


CAMERA_PIECES = ("gravity", "height")
"""What ``--camera-known`` may name (:data:`fruxel.train.models.conditioning.KNOWN`)."""
BIN_EDGES = {"height": (0.3, 1.9, 0.2, "m"), "pitch": (-20.0, 40.0, 10.0, "deg")}
"""``(first, last, step, unit)`` of ``--by-camera``'s bins per axis, for ``--help`` without importing torch (the same
as :data:`fruxel.train.eval.by_camera.HEIGHT_EDGES` and ``PITCH_EDGES``, tested)."""


def _edges_text(axis: str) -> str:
    first, last, step, unit = BIN_EDGES[axis]
    return f"{first:g} to {last:g} {unit} in {step:g} {unit} bins"


def camera_pieces(text: str) -> tuple[str, ...]:
    """argparse type of ``--camera-known``: ``none`` or a comma-separated subset of :data:`CAMERA_PIECES` (a height
    needs gravity)."""
    pieces = () if text == "none" else tuple(dict.fromkeys(t.strip() for t in text.split(",")))
    if any(p not in CAMERA_PIECES for p in pieces) or ("height" in pieces and "gravity" not in pieces):
        raise argparse.ArgumentTypeError(f"expected gravity,height, gravity or none, got {text!r}")
    return pieces


def _check_options(args: argparse.Namespace) -> None:
    """Options that do not go together, found before any work."""
    check_test_set_options(args)
    settings = args.camera_known or []
    for i, pieces in enumerate(settings):
        if pieces in settings[:i]:
            raise UsageError(f"--camera-known {','.join(pieces) or 'none'} is given twice")
    if args.data is None:
        if args.split != "test":
            raise UsageError("--split names a split of a data set: give --data DIR (streamed samples are the test "
                             "split)")
    else:
        given = [flag for flag, on in (("--seed", args.seed is not None), ("--no-augment", not args.augment)) if on]
        if given:
            verb = "describe" if len(given) > 1 else "describes"
            raise UsageError(f"{', '.join(given)} {verb} streamed samples; a data set (--data) has its own")
    if args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} is a file; --out is the folder for {', '.join(OUTPUTS)}")
    check_output_folder(args.out, "--out")
    if args.data is not None and not args.data.is_dir():
        raise UsageError(f"--data {args.data}: {'no such folder' if not args.data.exists() else 'not a folder'}")
    if args.backend is not None:
        from fruxel.kernels.registry import split_name

        split_name(args.backend)


# ---------------------------------------------------------------------------------------------------- prior
def prior_cache_path(data: Any, model: Any, samples: int) -> Path:
    """Where the per-cell prior of ``samples`` training samples of ``data`` for ``model`` is cached: a fruxel model
    file (:func:`fruxel.save`; its labels are the prior) named by a hash of everything that makes it.

    Args:
        data: the :class:`fruxel.train.samples.SampleSource`.
        model: the model's config (grid, image size, classes).
        samples: training samples counted.
    """
    from fruxel.io import cache_folder
    from fruxel.train.eval.sample_cache import code_digest, stream_key
    from fruxel.train.sim.manifest import MANIFEST

    key: dict[str, Any] = {"samples": samples, "grid": model.grid.to_dict(), "classes": model.classes.to_dict(),
                           "code": code_digest()}
    if data.source == "shards":
        # A data set's manifest holds its settings and every shard's SHA-256.
        key["data set"] = hashlib.sha256(Path(data.root, MANIFEST).read_bytes()).hexdigest()
    elif data.source == "folder":
        from fruxel.train.folder import folder_digest

        key["data folder"] = folder_digest(data.root)
    else:
        key.update(stream_key(data, model, (("train", samples),)))
    name = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:32]
    return cache_folder() / "prior" / f"{name}.npz"


def _cached_prior(path: Path, model: Any) -> Any:
    """The prior ``(D, H, W)`` uint8 cached at ``path``, or None (none there, unreadable, another grid)."""
    import fruxel

    try:
        m = fruxel.load(path)
    except fruxel.FruxelFileError:
        return None
    return m.labels if m.grid == model.grid and m.classes == model.classes else None


def _cache_prior(path: Path, mode: Any, model: Any) -> None:
    """Keep a prior at ``path`` (atomically); a cache that cannot be written is no error, only slower next time."""
    import fruxel
    from fruxel.io import remove_stale_temporaries

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(path)
        fruxel.save(path, fruxel.FruxelModel(mode, model.grid, model.classes))
    except OSError:
        pass


def _prior_mode(data: Any, model: Any, samples: int, batches: Any) -> Any:
    """The per-cell prior ``(D, H, W)`` uint8 of ``samples`` training samples: the cached one, else counted over
    ``batches()`` (``(images, labels)`` batches) and cached."""
    from fruxel.train.eval.baselines import CellPrior

    cache = prior_cache_path(data, model, samples)
    counted = _cached_prior(cache, model)
    if counted is None:
        prior = CellPrior(model.grid.shape, len(model.classes.names))
        for _, labels, *_ in batches():
            prior.add(labels)
        counted = prior.mode()
        _cache_prior(cache, counted, model)
    return counted


def _progress(batches: Iterator[Any], total: int, desc: str, quiet: bool) -> Iterator[Any]:
    """``batches`` with a progress bar over samples on stderr (hidden with ``--quiet`` or when stderr is no
    terminal)."""
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit="sample", disable=True if quiet else None, leave=False,
              dynamic_ncols=True) as bar:
        for b in batches:
            yield b
            bar.update(len(b[1]))


def _source(args: argparse.Namespace, mc: Any) -> tuple[Any, int]:
    """``(source, count)``: where the samples come from and how many are evaluated, checked against the model
    (:func:`fruxel.cli.common.streamed_source`)."""
    from fruxel.train.samples import DataError, split_size

    if args.data is None:
        return streamed_source(args, mc, augment=args.augment), args.samples or STREAM_SAMPLES
    source = data_source(args.data, mc)
    available = split_size(source, mc, args.split)
    count = args.samples or available
    if count > available:
        raise DataError(f"{args.data}: --samples {count}, but split {args.split!r} holds {available} samples")
    return source, count


def _prior(args: argparse.Namespace, source: Any, mc: Any, load: Any, device: Any) -> tuple[Any, dict[str, Any]]:
    """The per-cell prior's prediction rule and what it counted."""
    import numpy as np
    import torch

    from fruxel.train.eval.baselines import prior_prediction
    from fruxel.train.samples import DataError, split_size

    n_prior = args.prior_samples
    if source.source != "stream":
        try:
            n_prior = min(n_prior, split_size(source, mc, "train"))
        except DataError:
            raise DataError(f"{args.data}: the per-cell prior counts the train split, which this data set does "
                            "not have; give --prior-samples 0 to leave the prior out") from None
    counted = _prior_mode(source, mc, n_prior, lambda: load("train", n_prior, "prior"))
    mode = torch.from_numpy(np.array(counted, dtype=np.uint8)).to(device)  # a writable copy: torch warns otherwise
    return (lambda image, truth: prior_prediction(mode, len(truth))), {"split": "train", "samples": n_prior}


def _model_rules(args: argparse.Namespace, m: Any, device: Any) -> tuple[dict[str, Any], list[tuple[str, ...]]]:
    """The model's prediction rules by results key, and the camera-known settings they stand for: ``model`` under
    the first ``--camera-known`` setting, :func:`fruxel.train.eval.report.setting_key` under each further one; one
    rule and no settings for a model that reads no camera.

    Raises:
        UsageError: several settings for a model that reads no camera.
    """
    from fruxel.train.eval.evaluate import model_predict
    from fruxel.train.eval.report import setting_key

    settings = args.camera_known or [CAMERA_PIECES]
    autocast = device.type == "cuda"
    if not m.config.reads_camera:
        if len(settings) > 1:
            raise UsageError(f"--camera-known is given {len(settings)} times, but {m.path} reads no camera: every "
                             "setting would give the same numbers; give it once or not at all")
        return {"model": model_predict(m.network, m.rules, autocast=autocast)}, []
    keys = ["model", *(setting_key(known) for known in settings[1:])]
    return {k: model_predict(m.network, m.rules, autocast=autocast, camera_known=known)
            for k, known in zip(keys, settings, strict=True)}, settings


def _main(args: argparse.Namespace, argv: Sequence[str]) -> int:
    started = time.perf_counter()
    _check_options(args)
    import torch

    from fruxel.kernels.registry import describe
    from fruxel.render.table1 import machine_info
    from fruxel.train.engine.data import to_device
    from fruxel.train.eval.baselines import oracle_prediction
    from fruxel.train.eval.by_camera import CameraBinned, CameraBins
    from fruxel.train.eval.evaluate import evaluate_predictions, spread
    from fruxel.train.eval.report import build_report
    from fruxel.train.eval.sample_cache import cached_split_batches
    from fruxel.train.model_files import load_model
    from fruxel.train.samples import split_batches

    device = torch_device(args.device)
    m = load_model(args.checkpoint, device=device)
    mc = m.config
    source, count = _source(args, mc)
    # Warp device of the simulator's fruxelize (streaming).
    sim_device = "cuda" if device.type == "cuda" else "cpu"
    predictors, settings = _model_rules(args, m, device)
    # Camera records travel with the batches for a model that reads them, and for the bins of --by-camera.
    records = mc.reads_camera or args.by_camera

    def load(split: str, n: int, desc: str) -> Iterator[Any]:
        return _progress(split_batches(source, mc, split, n, args.batch, workers=args.workers, device=sim_device,
                                       camera=records), n, desc, args.quiet)

    def load_evaluated() -> Iterator[Any]:
        # Streamed samples are kept with their camera records whoever reads them, so every model shares one file.
        batches = cached_split_batches(source, mc, args.split, count, args.batch, workers=args.workers,
                                       device=sim_device, camera=source.source == "stream" or records)
        return _progress((b if records else b[:2] for b in batches), count, "evaluate", args.quiet)

    prior_info = None
    if args.prior_samples:
        predictors["prior"], prior_info = _prior(args, source, mc, load, device)
    predictors["oracle"] = lambda image, truth: oracle_prediction(truth, mc.grid, args.backend)
    binned = ({k: CameraBinned(len(mc.classes.names), CameraBins()) for k in predictors if k.startswith("model")}
              if args.by_camera else None)

    def as_input(pairs: Iterator[Any]) -> Iterator[Any]:
        for image, labels, *camera in pairs:
            yield (*to_device({"image": image, "labels": labels}, device), *camera)

    with torch.no_grad():
        # Examples spread over the samples: consecutive samples are frames of one room.
        shown = spread(count, args.examples)
        accs, kept = evaluate_predictions(predictors, as_input(load_evaluated()), mc.grid,
                                          mc.classes, device=device, backend=args.backend, keep=shown,
                                          by_camera=binned)
    machine = machine_info(str(device))
    machine.update(device=str(device), kernels=describe(args.backend, None, torch.zeros(1, device=device)))
    report = build_report(
        accs, mc.classes,
        model={"file": m.path, "architecture": mc.architecture, "grid": mc.grid.to_dict(),
               "image_size": list(mc.image_size), "training": m.training, "inference_rules": m.rules.to_dict()},
        data={"source": source.describe(), "kind": source.source, "root": source.root or None, "seed": source.seed,
              "augment": source.augment if source.source == "stream" else None, "split": args.split,
              "samples": count, "indices": f"indices 0..{count - 1}", "test_set": _test_set(source),
              "camera_known": list(settings[0]) if settings else None, "pack": _pack(source, mc, args.split, count)},
        prior=prior_info, machine=machine, command=shlex.join([PROG, *argv]),
        seconds=time.perf_counter() - started, examples="examples.png" if args.examples else None,
        by_camera=_by_camera(binned, mc))
    return _write(args, report, kept, mc, count)


def _pack(source: Any, mc: Any, split: str, count: int) -> str | None:
    """The report's ``data.pack``: the SHA-256 of the asset pack manifest streamed furnished rooms were drawn from
    (a pack built from other sources or code draws other rooms, so reports on two packs do not compare), else
    None."""
    if source.source != "stream":
        return None
    from fruxel.train.eval.sample_cache import pack_digest
    from fruxel.train.samples import sim_config

    return pack_digest(sim_config(mc, source, ((split, count),)))


def _by_camera(binned: dict[str, Any] | None, mc: Any) -> dict[str, Any] | None:
    """The report's ``by_camera`` section (None without ``--by-camera``)."""
    from fruxel.train.eval.by_camera import by_camera_section

    return None if binned is None else by_camera_section(binned, tuple(mc.classes.names), CHART)


def _test_set(source: Any) -> dict[str, str] | None:
    """The report's record of the source's test set: its name and description (None without one)."""
    from fruxel.train.sim.testsets import TEST_SETS

    if not source.test_set:
        return None
    return {"name": source.test_set, "description": TEST_SETS[source.test_set].description}


def _write(args: argparse.Namespace, report: dict[str, Any], kept: list[Any], mc: Any, count: int) -> int:
    """Write the report, its Markdown and the examples, then name them."""
    from fruxel.train.eval.report import markdown_report, rule_names
    from fruxel.train.eval.visual import example_sheet

    text = markdown_report(report)
    res = report["results"]
    names = rule_names(report)

    def miou(rule: str) -> str:
        v = res[rule]["miou"]
        return "n/a" if v is None else f"{v:.1f} %"

    title = (f"{Path(report['model']['file']).name}, {count} {args.split} samples: mIoU "
             + ", ".join(f"{names[r]} {miou(r)}" for r in res))
    out = args.out
    outputs = [
        (out / "report.md", lambda tmp: tmp.write_text(text, encoding="utf-8")),
        # default=str: a training summary read from a checkpoint may hold values JSON has no type for.
        (out / "report.json", lambda tmp: tmp.write_text(json.dumps(report, indent=2, default=str) + "\n",
                                                          encoding="utf-8")),
    ]
    if args.examples:
        outputs.append((out / "examples.png", lambda tmp: example_sheet(kept, mc.grid, mc.classes, tmp, title=title,
                                                                        backend=args.backend)))
    if report["by_camera"]:
        outputs.append((out / CHART, lambda tmp: _chart(report, tmp, f"{Path(report['model']['file']).name}, "
                                                                 f"{count} {args.split} samples")))
    written = write_outputs(outputs)
    if not args.quiet:
        print(title)
        for p in written:
            print(p)
    return 0


def _chart(report: dict[str, Any], path: Path, title: str) -> None:
    """Draw the report's ``by_camera`` section: a line style per camera-known setting of a model that reads the
    camera, one unnamed curve per metric for a model that reads none."""
    from fruxel.train.eval.by_camera import camera_chart
    from fruxel.train.eval.report import SETTING, setting_text

    rules = report["by_camera"]["height"]["miou"]
    known = report["data"]["camera_known"]
    labels = {r: ("" if known is None else "camera known: " + (setting_text(known) if r == "model"
                                                                else r[len(SETTING):])) for r in rules}
    camera_chart(report["by_camera"], labels, path, title=title)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``fruxel-eval`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    return run(lambda args: _main(args, argv), build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
