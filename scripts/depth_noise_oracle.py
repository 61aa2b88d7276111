"""How precise a perfect reader's depth must be: per-class IoU of a test set's truth against the same truth with
each column's depth made wrong by a relative error.

    python scripts/depth_noise_oracle.py [--model ssz64-any] [--test-set any-camera] [--samples 256]
                                         [--sigma 0,0.01,0.02,0.03,0.05,0.1] [--rel]

The metric counts exact cells: a 64^3 grid over 0.5-8 m has slices 0.117 m deep, 3 % of the distance at 4 m. A
reader that knew every cell's class, the hidden ones too, but saw each column of the grid's own view at a depth
``(1 + e)`` times the true one, answers the truth stretched along that column: the cell at depth ``z`` takes the
true label at ``z / (1 + e)`` (of the slice that depth lies in; empty where it lies outside the grid). With ``e`` drawn
per column from ``N(0, sigma)``, its IoU against the truth is what depth of that relative precision leaves even a
reader perfect in everything else. The expected counts depend only on each column's ``e``, so independent columns
stand for any spatially smooth error of the same spread. The samples are fruxel-eval's (the same stream, seed 0,
augmented, its sample cache: run after a `fruxel-eval` of the same test set and count), for ``--model``'s grid and
image. An analysis for the experiments log, not a metric of the product's reports.

With ``--rel``, the model's own first-surface depth on the same samples is measured for comparison: per column
of the grid's own view where both the prediction and the truth have an occupied cell, the relative error
``z_pred / z_true - 1`` of the first ones' slice centres, as REL (the mean of its absolute value, the usual
single-image depth metric), the spread ``sigma`` of a Gaussian with that REL (``REL / sqrt(2 / pi)``) and the
median absolute error (a wrong first object, the wall behind a missed chair, weighs on the mean).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from depth_tolerance import tolerant_counts, tolerant_iou  # noqa: E402


def stretched(truth: np.ndarray, error: np.ndarray, z_near: float, dz: float) -> np.ndarray:
    """``truth`` seen at a depth ``1 + error`` times the true one, column by column.

    Args:
        truth: ``(B, D, H, W)`` uint8 labels, grid frame (slice ``k`` centred at ``z_near + (k + 0.5) dz``).
        error: ``(B, H, W)`` float relative depth error of each column (``> -1``).
        z_near: depth of the grid's first slice's near face, metres.
        dz: slice depth, metres.

    Returns:
        ``(B, D, H, W)`` uint8: cell ``k`` holds the truth's label at depth ``z_k / (1 + error)`` (of the slice it
        lies in), 0 (empty) where that depth lies outside the grid.
    """
    depth = truth.shape[1]
    z = z_near + (np.arange(depth) + 0.5) * dz
    source = (z[None, :, None, None] / (1.0 + error[:, None]) - z_near) / dz
    k = np.floor(source).astype(np.int64)
    inside = (k >= 0) & (k < depth)
    out = np.take_along_axis(truth, np.clip(k, 0, depth - 1), axis=1)
    out[~inside] = 0
    return out


def truths(model: str, test_set: str, samples: int, batch: int) -> tuple[tuple[str, ...], tuple[float, float],
                                                                              Iterator[np.ndarray]]:
    """The class names, the grid's ``(z_near, dz)`` and the ``(B, D, H, W)`` uint8 truth of fruxel-eval's first
    ``samples`` test samples of ``test_set`` for ``model``'s grid and image (its config), batch by batch."""
    from fruxel.train.eval.sample_cache import cached_split_batches
    from fruxel.train.model_files import load_model
    from fruxel.train.samples import SampleSource

    config = load_model(model, device="cpu").config
    source = SampleSource(seed=0, assets="", test_set=test_set, augment=True)
    grid = config.grid

    def batches() -> Iterator[np.ndarray]:
        for _, labels, _ in cached_split_batches(source, config, "test", samples, batch, device="cpu", camera=True):
            yield labels.numpy()

    return tuple(config.classes.names), (float(grid.z_near), float(grid.dz)), batches()


def oracle_miou(batches: Iterator[np.ndarray], classes: int, z_near: float, dz: float, sigmas: list[float],
                seed: int = 0) -> list[tuple[float, np.ndarray]]:
    """Per sigma, the mIoU (percent, over the classes present in the truth) and the per-class IoU ``(classes,)``
    of the truth against itself stretched by per-column errors ``N(0, sigma)`` (:func:`stretched`)."""
    rng = np.random.default_rng(seed)
    counts = {s: np.zeros((classes, 4), dtype=np.int64) for s in sigmas}
    for truth in batches:
        for s in sigmas:
            error = np.clip(rng.normal(0.0, s, (truth.shape[0],) + truth.shape[2:]), -0.9, None)
            counts[s] += tolerant_counts(stretched(truth, error, z_near, dz), truth, classes, 0)
    out = []
    for s in sigmas:
        iou = tolerant_iou(counts[s])
        present = counts[s][:, 1] > 0
        out.append((float(np.nanmean(iou[present])), iou))
    return out


def first_surface_errors(pred: np.ndarray, truth: np.ndarray, z_near: float, dz: float) -> np.ndarray:
    """Relative depth errors ``z_pred / z_true - 1`` of the first occupied cells of the columns where both
    ``(B, D, H, W)`` label volumes have one: ``(N,)`` float64 (slice centres, grid frame)."""
    hit_p, hit_t = pred != 0, truth != 0
    both = hit_p.any(axis=1) & hit_t.any(axis=1)
    kp, kt = hit_p.argmax(axis=1)[both], hit_t.argmax(axis=1)[both]
    return (z_near + (kp + 0.5) * dz) / (z_near + (kt + 0.5) * dz) - 1.0


def with_model_errors(model: str, test_set: str, samples: int, batch: int, z_near: float, dz: float,
                      errors: list[np.ndarray]) -> Iterator[np.ndarray]:
    """The truths of the held-out samples, batch by batch, as :func:`truths` gives them, read with ``model``'s
    predictions (told the camera's gravity and height) in the same pass: each batch's first-surface errors
    (:func:`first_surface_errors`) are appended to ``errors``."""
    from depth_tolerance import held_out_predictions

    _, pairs = held_out_predictions(model, test_set, samples, batch, "gravity,height")
    for pred, truth in pairs:
        errors.append(first_surface_errors(pred, truth, z_near, dz))
        yield truth


def _parser() -> argparse.ArgumentParser:
    from fruxel.cli.common import OneLineParser

    p = OneLineParser(prog="depth_noise_oracle.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--test-set", default="any-camera")
    p.add_argument("--samples", type=int, default=256)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--sigma", default="0,0.01,0.02,0.03,0.05,0.1",
                   help="comma-separated relative depth errors (standard deviations)")
    p.add_argument("--model", default="ssz64-any",
                   help="the model whose grid and samples to use: a shipped name or a .safetensors file")
    p.add_argument("--rel", action="store_true", help="also measure the model's own first-surface REL")
    return p


def _main(args: argparse.Namespace) -> int:
    from fruxel.cli.common import UsageError

    try:
        sigmas = [float(s) for s in args.sigma.split(",")]
    except ValueError:
        raise UsageError(f"--sigma: not a list of numbers: {args.sigma!r}") from None
    if any(not 0 <= s < 1 for s in sigmas):
        raise UsageError(f"--sigma: each must be in [0, 1): {args.sigma!r}")
    if args.samples < 1 or args.batch < 1:
        raise UsageError(f"--samples and --batch must be at least 1, got {args.samples} and {args.batch}")
    names, (z_near, dz), batches = truths(args.model, args.test_set, args.samples, args.batch)
    errors: list[np.ndarray] = []
    if args.rel:
        batches = with_model_errors(args.model, args.test_set, args.samples, args.batch, z_near, dz, errors)
    for s, (miou, iou) in zip(sigmas, oracle_miou(batches, len(names), z_near, dz, sigmas), strict=True):
        print(f"sigma {100 * s:g} %: mIoU {miou:.1f} | "
              + " ".join(f"{names[c]} {iou[c]:.1f}" for c in range(1, len(names))))
    if args.rel:
        absolute = np.abs(np.concatenate(errors))
        rel, median = float(absolute.mean()), float(np.median(absolute))
        print(f"{args.model}, camera told: first-surface REL {100 * rel:.1f} % (a Gaussian's sigma "
              f"{100 * rel / np.sqrt(2 / np.pi):.1f} %), median {100 * median:.1f} %")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv``, print the table; bad input is one error line and status 2 (fruxel's commands' runner)."""
    from fruxel.cli.common import run

    return run(_main, _parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
