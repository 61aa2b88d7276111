"""Inference rules: what is applied to a network's output after it, kept apart from the network (conventions
section 8), with their own stored settings (:class:`InferenceRules`, under the ``rules`` key of a shipped model
file).

:func:`predict_logits` is the one place a network's prediction becomes a model's answer: the network on the image
(and, with ``flip_average``, on its mirror image, the two averaged), then :func:`apply_rules` (the empty-logit
offset, :func:`fill_columns`, :func:`first_hit_label`). The :class:`~fruxel.train.predict.Predictor`, the
evaluation, the calibration (``fruxel-calibrate``) and the live demo all call it. Training never does: the
objective reads the network's raw output.

The rules read the network's output contract (:class:`~fruxel.train.models.registry.ModelOutput`); ``fill_columns``
needs its column depth head.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F

from fruxel.errors import ConfigError

from .models.registry import run_network

DEFAULT_FILL_THRESHOLD = 0.5
"""The default ``threshold`` of :func:`fill_columns`."""


@dataclass(frozen=True)
class InferenceRules:
    """The rules a trained model's logits pass through at inference, in the order applied. The defaults apply
    none: the network's argmax as it is. A shipped model stores the rules chosen for it after training on
    training-split samples (``fruxel-calibrate``)."""

    flip_average: bool = False
    """Predict the image and its mirror image (left and right swapped; one batch on a GPU, two passes on the CPU)
    and average the outputs, the mirror's mirrored back (twice the network's work). The grid's own camera is
    centred (conventions section 1), so the mirror image is the mirrored room seen through the mirrored grid."""
    empty_offset: float = 0.0
    """Added to every cell's empty logit (channel 0): a decision threshold between empty and occupied, since the
    class-weighted cross-entropy that trains the model down-weights the empty class."""
    fill_columns: bool = False
    """Give a column that the volume leaves empty one surface cell when the column depth head says it has a surface
    (:func:`fill_columns`; needs a network with a column depth head)."""
    fill_threshold: float = DEFAULT_FILL_THRESHOLD
    """``fill_columns`` fills a column whose depth head gives "no surface" a probability below this, in (0, 1]
    (1 fills every column the volume leaves empty)."""
    first_hit_label: bool = False
    """Last: give each column's first occupied cell the class most likely to be the column's first hit
    (:func:`first_hit_label`), which is what the grid's own camera shows of it."""

    def __post_init__(self) -> None:
        for name in ("flip_average", "fill_columns", "first_hit_label"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"rules.{name} must be true or false, got {getattr(self, name)!r}")
        if isinstance(self.empty_offset, bool) or not isinstance(self.empty_offset, (int, float)) \
                or not math.isfinite(self.empty_offset):
            raise ConfigError(f"rules.empty_offset must be a finite number, got {self.empty_offset!r}")
        t = self.fill_threshold
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (math.isfinite(t) and 0.0 < t <= 1.0):
            raise ConfigError(f"rules.fill_threshold must be in (0, 1], got {t!r}")

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (the ``rules`` metadata of a shipped model file)."""
        return {"flip_average": self.flip_average, "empty_offset": float(self.empty_offset),
                "fill_columns": self.fill_columns, "fill_threshold": float(self.fill_threshold),
                "first_hit_label": self.first_hit_label}

    @classmethod
    def from_dict(cls, d: Any) -> InferenceRules:
        """Inverse of :meth:`to_dict` (missing keys take their defaults).

        Raises:
            ConfigError: not an object, an unknown key or an impossible value.
        """
        from .config import override

        return override(cls(), d, "rules")


NO_RULES = InferenceRules()
"""No rule: the network's argmax as it is."""


def predict_logits(network: torch.nn.Module, image: torch.Tensor, rules: InferenceRules, *,
                   batched_flip: bool | None = None, camera: Any = None) -> torch.Tensor:
    """A model's answer for a batch: the network's logits under ``rules`` (see the module docstring).

    Args:
        network: a network honouring the output contract (:class:`~fruxel.train.models.registry.ModelOutput`), in
            the mode the caller wants (eval for inference).
        image: ``(B, 3, h, w)`` float RGB in [0, 1], the network's image size.
        rules: the rules.
        batched_flip: with ``flip_average``, run the image and its mirror image as one batch of 2 B (True) or as
            two passes (False); None: one batch on a GPU, two passes on the CPU, where the batch of two is
            cache-bound and slower (BENCHMARKS.md).
        camera: what is known of the batch's camera (a
            :class:`~fruxel.train.models.conditioning.CameraInput`), for a network that reads it; None for others.
            The mirror image's camera is its mirror (:meth:`~fruxel.train.models.conditioning.CameraInput.mirrored`).

    Returns:
        ``(B, C, D, H, W)`` logits in the network's output dtype, grid frame.

    Raises:
        ValueError: ``fill_columns`` with a network that has no column depth head.
    """
    if rules.flip_average:
        out = mirror_average(network, image, image.device.type != "cpu" if batched_flip is None else batched_flip,
                             camera)
    else:
        out = run_network(network, image, camera)
    return apply_rules(out.logits, out.depth_logits, rules)


def mirror_average(network: torch.nn.Module, image: torch.Tensor, batched: bool, camera: Any = None) -> Any:
    """The network's output on the image and on its mirror image (W reversed), averaged, the mirror's outputs
    mirrored back along W (the last axis of every output: conventions section 1, ``cx = W / 2``, so pixel column
    x and grid column W - 1 - x mirror each other exactly).

    Args:
        network: the network.
        image: ``(B, 3, h, w)`` float RGB.
        batched: one pass over a batch of 2 B, or two passes.
        camera: the batch's camera for a network that reads it (the mirror image takes its mirror), else None.

    Returns:
        The network's output type with every tensor field averaged (None fields stay None).
    """
    mirror = None if camera is None else camera.mirrored()
    if batched:
        b = image.shape[0]
        both = run_network(network, torch.cat([image, image.flip(-1)]), None if camera is None else camera.cat(mirror))
        pairs = {k: (None, None) if v is None else (v[:b], v[b:]) for k, v in vars(both).items()}
        kind = type(both)
    else:
        a, m = run_network(network, image, camera), run_network(network, image.flip(-1), mirror)
        pairs = {k: (v, getattr(m, k)) for k, v in vars(a).items()}
        kind = type(a)
    return kind(**{k: None if x is None else (x + y.flip(-1)) * 0.5 for k, (x, y) in pairs.items()})


def apply_rules(logits: torch.Tensor, depth_logits: torch.Tensor | None, rules: InferenceRules) -> torch.Tensor:
    """``rules``' empty-logit offset, :func:`fill_columns` and :func:`first_hit_label` on a batch's logits (not
    ``flip_average``, which concerns the network's passes: :func:`predict_logits`).

    Args:
        logits: ``(B, C, D, H, W)`` class logits before the rules (channel 0 = empty), any float dtype.
        depth_logits: ``(B, D + 1, H, W)`` column depth logits (needed with ``fill_columns``).
        rules: the rules.

    Returns:
        ``(B, C, D, H, W)`` logits, ``logits``' dtype (``logits`` itself when there is nothing to do).

    Raises:
        ValueError: ``fill_columns`` without ``depth_logits``.
    """
    if rules.fill_columns and depth_logits is None:
        raise ValueError("the fill_columns rule needs a network with a column depth head")
    ruled = shift_and_fill(logits, depth_logits, empty_offset=rules.empty_offset, fill=rules.fill_columns,
                           fill_threshold=rules.fill_threshold)
    return first_hit_label(ruled, logits) if rules.first_hit_label else ruled


def first_hit_log_probs(logits: torch.Tensor, empty_offset: float = 0.0) -> torch.Tensor:
    """Each column's distribution of the own view's first hit, from the cells' class distributions taken as
    independent: ``P(first hit = c) = sum_k P(cells 0..k-1 empty) P(cell k = c)`` and ``P(miss) = P(all empty)``.

    This is what the grid's own camera sees of the volume in expectation (a column is a pixel of the own view,
    conventions section 1), the own-view term of the shell-aware losses without their kernels. The training objective's
    ``first_hit`` term is its cross-entropy against the truth's first label; the ``first_hit_label`` inference rule
    takes its argmax over the occupied classes.

    Args:
        logits: ``(B, C, D, H, W)`` class logits (channel 0 = empty), any float dtype, grid frame.
        empty_offset: added to every cell's empty logit first.

    Returns:
        ``(B, C, H, W)`` float32 log-probabilities: channel 0 the column's miss, channel c its first hit being
        class c; they sum to 1 over the channels.
    """
    s = logits.float()
    if empty_offset:
        s = torch.cat([s[:, :1] + empty_offset, s[:, 1:]], dim=1)
    log_p = torch.log_softmax(s, dim=1)
    empty = log_p[:, 0]  # (B, D, H, W)
    through = torch.cumsum(empty, dim=1)  # log P(cells 0..k empty)
    # log P(cells 0..k-1 empty): the exclusive sum, shifted rather than subtracted (a cell surely occupied would
    # subtract a log of 0).
    before = torch.cat([torch.zeros_like(through[:, :1]), through[:, :-1]], dim=1)
    hit = torch.logsumexp(before.unsqueeze(1) + log_p[:, 1:], dim=2)  # (B, C - 1, H, W)
    return torch.cat([through[:, -1:], hit], dim=1)


def first_hit_classes(raw: torch.Tensor) -> torch.Tensor:
    """Each column's most likely first-hit class among the occupied ones, ``argmax_{c >= 1}`` of
    :func:`first_hit_log_probs` of the raw logits ``(B, C, D, H, W)``: ``(B, H, W)`` int64 in ``[1, C)``."""
    return first_hit_log_probs(raw)[:, 1:].argmax(dim=1) + 1


def first_hit_label(logits: torch.Tensor, raw: torch.Tensor | None, *, best: torch.Tensor | None = None
                    ) -> torch.Tensor:
    """Give each column's first occupied cell the class most likely to be the column's first hit.

    The argmax of each cell alone decides where a column's first occupied cell is and what it holds; the own
    camera sees the first hit of the whole column. A board thinner than a cell, which the truth keeps only where it
    crosses a cell centre, is often spread by the decoder over several cells, none of them more likely occupied
    than empty, so the argmax shows the wall behind it; together those cells can still make furniture the likeliest
    first hit. This rule takes the class ``c >= 1`` that maximises ``P(first hit = c)`` of
    :func:`first_hit_log_probs` on the raw logits (the distribution the ``first_hit`` loss trains) and raises its
    logit in the first occupied cell of ``logits`` just above that cell's best, so that the argmax is that class.
    Only that cell's class can change: the volume's occupancy, the cells behind it and every logit of a cell whose
    class stays are untouched, and empty columns stay empty.

    Args:
        logits: ``(B, C, D, H, W)`` logits after the other rules (:func:`shift_and_fill`), any float dtype, grid
            frame.
        raw: ``(B, C, D, H, W)`` the network's logits before them (the same or another float dtype); None when
            ``best`` is given.
        best: ``(B, H, W)`` int64, :func:`first_hit_classes` of ``raw`` computed beforehand (a sweep over the other
            rules needs it once).

    Returns:
        ``(B, C, D, H, W)`` logits, ``logits``' dtype.
    """
    # A cell is occupied where its argmax is not empty (a tie goes to empty, as argmax takes the first), as in
    # fill_columns; compared through the best occupied logit because on the CPU an argmax across the channel axis
    # is many times slower than the maximum.
    occupied = logits[:, 1:].amax(dim=1) > logits[:, 0]  # (B, D, H, W)
    first = occupied.to(torch.uint8).argmax(dim=1, keepdim=True)  # (B, 1, H, W): the first occupied slice (0: none)
    if best is None:
        best = first_hit_classes(raw)
    # Only the first occupied cell of each column is read and written: (B, C, 1, H, W) gathered along depth.
    index = first.unsqueeze(1).expand(-1, logits.shape[1], -1, -1, -1)
    cell = logits.gather(2, index)
    change = occupied.any(dim=1, keepdim=True) & (cell.argmax(dim=1) != best.unsqueeze(1))  # (B, 1, H, W)
    mask = F.one_hot(best, logits.shape[1]).permute(0, 3, 1, 2).unsqueeze(2).bool() & change.unsqueeze(1)
    top = cell.amax(dim=1, keepdim=True)
    # Just above the cell's best, by a margin wider than the dtype's spacing at that size (bfloat16 keeps 8 bits).
    return logits.scatter(2, index, torch.where(mask, top + (1.0 + 0.02 * top.abs()), cell))


def shift_and_fill(logits: torch.Tensor, depth_logits: torch.Tensor | None, *, empty_offset: float,
                    fill: bool, fill_threshold: float = DEFAULT_FILL_THRESHOLD) -> torch.Tensor:
    """The rules :attr:`InferenceRules.empty_offset`, ``fill_columns`` and ``fill_threshold`` on a batch's logits.

    Args:
        logits: ``(B, C, D, H, W)`` class logits (channel 0 = empty), any float dtype.
        depth_logits: ``(B, D + 1, H, W)`` column depth logits (needed with ``fill``).
        empty_offset: added to every cell's empty logit.
        fill: then :func:`fill_columns`.
        fill_threshold: its ``threshold``.

    Returns:
        ``(B, C, D, H, W)`` logits (``logits`` itself when there is nothing to do).
    """
    if fill:
        return fill_columns(logits, depth_logits, empty_offset, fill_threshold)
    if empty_offset:
        return torch.cat([logits[:, :1] + empty_offset, logits[:, 1:]], dim=1)
    return logits


def fill_columns(logits: torch.Tensor, depth_logits: torch.Tensor, empty_offset: float = 0.0,
                 threshold: float = DEFAULT_FILL_THRESHOLD) -> torch.Tensor:
    """Give every column that the depth head believes has a surface at least one occupied cell.

    The argmax of a column's logits can leave it empty everywhere while the column depth head is confident that
    the own camera sees a surface there: typically a plain wall close to the camera, whose distance the decoder
    spreads over many slices so that no single cell is more likely occupied than empty, and the predicted model
    shows a hole (how often, for the model shipped before this rule existed: docs/experiments.md). For such a
    column (no cell with ``argmax != 0``, and the depth head's probability of "no surface" below ``threshold``) the
    cell with the largest ``P(occupied) = 1 - P(empty)`` has its empty logit lowered just below its best occupied
    class's, so that it becomes that class's surface; every other logit is returned unchanged.
    Columns that the volume already fills, and columns that the head thinks see nothing, are untouched.

    Args:
        logits: ``(B, C, D, H, W)`` class logits (channel 0 = empty), any float dtype, grid frame.
        depth_logits: ``(B, D + 1, H, W)`` float logits of each column's first-surface slice (bin D = no surface).
        empty_offset: added to every cell's empty logit first (:attr:`InferenceRules.empty_offset`; the same as
            calling this on the shifted logits, in one pass).
        threshold: fill a column whose "no surface" probability is below this
            (:attr:`InferenceRules.fill_threshold`, in (0, 1]; 1 fills every empty column but those where the head is
            certain of "no surface").

    Returns:
        ``(B, C, D, H, W)`` logits, ``logits``' dtype.
    """
    empty = logits[:, 0] + empty_offset if empty_offset else logits[:, 0]
    occupied = logits[:, 1:]
    top = occupied.amax(dim=1)  # (B, D, H, W): the best occupied class's logit
    no_surface = torch.softmax(depth_logits.float(), dim=1)[:, -1]  # (B, H, W)
    filled = filled_empty_logits(empty, top, torch.logsumexp(occupied.float(), dim=1), no_surface, threshold)
    return torch.cat([filled.unsqueeze(1), occupied], dim=1)


def filled_empty_logits(empty: torch.Tensor, top: torch.Tensor, occupied_lse: torch.Tensor, no_surface: torch.Tensor,
                        threshold: float) -> torch.Tensor:
    """The empty logits after :func:`fill_columns`, from the per-cell quantities it reads (a sweep over offsets and
    thresholds computes them once a batch: :func:`fruxel.train.eval.calibrate.swept_predictions`).

    Args:
        empty: ``(B, D, H, W)`` empty logits, the offset added.
        top: ``(B, D, H, W)`` the best occupied class's logit.
        occupied_lse: ``(B, D, H, W)`` float32 log-sum-exp of the occupied classes' logits.
        no_surface: ``(B, H, W)`` the depth head's "no surface" probability.
        threshold: :attr:`InferenceRules.fill_threshold`.

    Returns:
        ``(B, D, H, W)`` the empty logits, lowered just below ``top`` in each filled column's chosen cell.
    """
    fill = ~(top > empty).any(dim=1) & (no_surface < threshold)
    # log P(occupied) - log P(empty) rises with P(occupied): one log-sum-exp, over the occupied classes only.
    odds = occupied_lse - empty.float()
    cell = torch.zeros_like(empty, dtype=torch.bool).scatter_(1, odds.argmax(dim=1, keepdim=True), fill.unsqueeze(1))
    # Just below the best class, by a margin wider than the dtype's spacing at that size (bfloat16 keeps 8 bits).
    return torch.where(cell, top - (1.0 + 0.02 * top.abs()), empty)
