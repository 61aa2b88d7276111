"""The generated tables of the model card, ``docs/model.md``, and of the README's results, from the stored evaluation
reports and the shipped models.

    python scripts/model_card.py            # rewrite the card's generated tables in place
    python scripts/model_card.py --check    # exit status 1, naming the tables, when the card is out of date

The card marks every generated table with two comments; what lies between them belongs to this script:

    <!-- generated: headline -->
    | metric | ... |

    <!-- end -->

Each number comes from the one file that holds it: results from the ``fruxel-eval`` reports in ``docs/eval/``
(:data:`SHIPPED` and the candidates' :class:`Pool` s name which reports are a model's test sets; the sets of a pool
are counted together from their confusion matrices and pixel counts, as ``fruxel-eval`` counts one set), sizes,
training and inference rules from the metadata and tensors of the shipped models ``train/data/*.safetensors``.

Bad input (a card without a table or with a marker the script does not know, a missing or malformed report, reports
that are not on the samples their table compares) is one error line naming the file, exit status 2, nothing written.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fruxel.cli.common import OneLineParser, run, write_outputs
from fruxel.errors import FruxelError

ROOT = Path(__file__).resolve().parents[1]
START = re.compile(r"^<!-- generated: ([a-z0-9-]+) -->$")
"""The line that opens a generated table; the group is the table's name (a key of :data:`TABLES`)."""
END = "<!-- end -->"
"""The line that closes it."""
SAMPLES_PER_ROOM = 16
"""Views the simulator draws per room in the test splits of the reports (the rooms column of the per-set tables)."""
TARGETS = {"miou": "50", "completion_iou": "60", "own_view_accuracy": "97"}
"""The targets set for the shipped models (percent), by metric."""
METRICS = (("miou", "mIoU (%)", 1), ("completion_iou", "completion IoU (%)", 1),
           ("own_view_accuracy", "own-view first-hit accuracy (%)", 2),
           ("novel_view_accuracy", "novel-view first-hit accuracy (%)", 1),
           ("depth_error", "novel-view depth error (m)", 3))
"""``(key of a report's results, name, decimals)`` of the summary metrics."""
REPORT_KEYS = (("results", "model"), ("data", "split"), ("data", "seed"), ("data", "samples"), ("model", "grid"),
               ("model", "image_size"), ("classes", "names"))
"""What the tables read of every report (as key paths)."""
COUNTS = ("own_hits", "own_correct", "novel_pixels", "novel_correct", "depth_pixels", "depth_abs_sum")
"""The pixel counts of a result, from which its view metrics are computed."""
RESULT_KEYS = (("confusion",), ("samples",), *(("counts", k) for k in COUNTS))
"""What they read of each of its results (model, prior, oracle)."""
BN_STATISTICS = ("running_mean", "running_var", "num_batches_tracked")
"""Tensor name endings of BatchNorm's running statistics: stored with the weights, not parameters."""


class CardError(FruxelError, ValueError):
    """A card, report or model file this script cannot use; the message names the file."""


@dataclass(frozen=True)
class Pool:
    """A model's results on test sets that do not overlap, counted together."""

    label: str
    """The model's name in the tables."""
    reports: tuple[str, ...]
    """File names in the reports folder, one per test set."""
    about: str = ""
    """What the model is, in words (candidates' tables); ``{image}`` stands for the size of the image it reads."""


@dataclass(frozen=True)
class Shipped:
    """A shipped model and the reports that measure it."""

    file: str
    """Its file in the models folder."""
    pool: Pool
    """Its test sets."""
    prior: str
    """A report on samples among the pool's whose ``prior`` result is the per-cell prior at this model's grid (the
    prior does not depend on the model, only on the grid and the training split)."""
    extra: tuple[tuple[str, str], ...] = ()
    """``(report, what)``: more reports of this model on samples inside the pool's, shown as rows of its own."""


def _seeds(pattern: str) -> tuple[str, ...]:
    return tuple(pattern.format(s) for s in range(1, 7))


SHIPPED = {
    "ssz64": Shipped("ssz64.safetensors",
                     Pool("ssz64", ("ssz64-test8192.json", *_seeds("ssz64-test-seed{}-2048.json")),
                          "shipped: ft15 with a detail branch, reading a {image} image, trained on"),
                     prior="ssz64-ft15-test8192.json",
                     extra=(("ssz64-test1024.json", "seed 0, its first 1,024 alone (on the CPU)"),)),
    "ssz128": Shipped("ssz128.safetensors",
                      Pool("ssz128", ("ssz128-test1024.json", *_seeds("ssz128-test-seed{}-2048.json"))),
                      prior="paper128-test1024.json"),
}
"""The shipped models by name."""


@dataclass(frozen=True)
class CameraAware:
    """A shipped model that reads the camera, and the reports that measure it: one per test set, each with the
    model under every camera setting it was evaluated with (its rows are not counted together: the sets differ in
    what they test)."""

    file: str
    """Its file in the models folder."""
    reports: tuple[str, ...]
    """File names in the reports folder."""


CAMERA_AWARE = {
    "ssz64-any": CameraAware("ssz64-any.safetensors", ("ssz64-any-any-camera-2048.json",
                                                       "ssz64-any-test-assets-2048.json", "ssz64-any-robot-2048.json")),
}
"""The shipped camera-aware models by name (issue 39's; ssz64-any is the default model)."""
MODEL_FILES = {**{n: s.file for n, s in SHIPPED.items()}, **{n: c.file for n, c in CAMERA_AWARE.items()}}
"""Every shipped model's file by name."""
CANDIDATES = (
    Pool("ft15", ("ssz64-ft15-test8192.json", *_seeds("ssz64-ft15-test-seed{}-2048.json")),
         "shipped before ssz64: the same network without the detail branch, reading a {image} image"),
    SHIPPED["ssz64"].pool,
    Pool("ft19d", ("ssz64-ft19d-test8192.json", *_seeds("ssz64-ft19d-test-seed{}-2048.json")),
         "ssz64 trained on, on fresh rooms, with the same recipe"),
    Pool("ft20g", tuple(f"ssz64-ft20g-seed{s}.json" for s in range(7)),
         "ssz64 trained on with a second depth head that places each column's surface within its slice, "
         "supervised with the renderer's depth"),
    Pool("x1", ("ssz64-x1-test8192.json", *_seeds("ssz64-x1-test-seed{}-2048.json")),
         "ssz64 with a level that reads a {image} image for the same 64^3 cells (the rest frozen)"),
)
"""64^3 models evaluated on ssz64's test sets, the shipped one among them (not shipped: see docs/experiments.md)."""
LEVEL = (
    Pool("ssz128", ("ssz128-test1024.json",), "shipped: the level, then the whole network, trained"),
    Pool("r1", ("ssz128-r1-test1024.json",), "the level trained alone, the 64^3 network frozen"),
    Pool("fresh level", ("ssz128-fresh-level-test1024.json",),
         "the level as it starts: ssz64's answer repeated over 2 x 2 x 2 finer cells"),
    Pool("paper preset", ("paper128-test1024.json",),
         "a smaller 128^3 network trained from scratch, not grown from ssz64"),
)
"""128^3 models on the same 1,024 test samples: what the refinement level adds."""


# ---------------------------------------------------------------------------------------------------- sources
class Sources:
    """The reports and shipped models the tables read, each loaded once.

    Args:
        reports: the folder of the ``fruxel-eval`` reports.
        models: the folder of the shipped ``.safetensors`` models.
    """

    def __init__(self, reports: Path, models: Path) -> None:
        self.reports_dir, self.models_dir = reports, models
        self._reports: dict[str, dict[str, Any]] = {}
        self._models: dict[str, dict[str, Any]] = {}

    def report(self, name: str) -> dict[str, Any]:
        """The report ``name``, checked: a ``fruxel-eval-report`` of version 1 with the model's counts."""
        if name not in self._reports:
            self._reports[name] = _read_report(self.reports_dir / name)
        return self._reports[name]

    def model(self, name: str) -> dict[str, Any]:
        """The shipped model ``name`` (a key of :data:`MODEL_FILES`): ``meta`` (the metadata, JSON decoded),
        ``rules``, ``parameters``, ``level_parameters``, ``dtypes`` and ``bytes``."""
        if name not in self._models:
            self._models[name] = _read_model(self.models_dir / MODEL_FILES[name])
        return self._models[name]

    def pool(self, pool: Pool, rule: str = "model") -> tuple[Any, list[tuple[dict[str, Any], Any]]]:
        """One rule's counts over a pool's sets: the total and, per set, the report and its accumulator."""
        sets = [(r, _accumulator(r, rule)) for r in (self.report(n) for n in pool.reports)]
        keys = [_samples_key(r) for r, _ in sets]
        if len(set(keys)) != len(keys):
            raise CardError(f"{pool.label}: two of its reports are on the same samples: {', '.join(pool.reports)}")
        total = _empty_like(sets[0][1])
        for _, acc in sets:
            total.merge(acc)
        return total, sets


def _read_report(path: Path) -> dict[str, Any]:
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise CardError(f"{path}: cannot read the report: {getattr(e, 'strerror', None) or e}") from None
    if not isinstance(report, dict) or report.get("format") != "fruxel-eval-report" or report.get("version") != 1:
        raise CardError(f"{path}: not a fruxel-eval report of version 1")
    rules = report.get("results") if isinstance(report.get("results"), dict) else {}
    needed = [*REPORT_KEYS, *(("results", r, *k) for r in rules for k in RESULT_KEYS)]
    for keys in needed:
        value: Any = report
        for key in keys:
            if not isinstance(value, dict) or key not in value:
                raise CardError(f"{path}: not a fruxel-eval report: no {'.'.join(keys)}")
            value = value[key]
    report["_path"] = str(path)
    return report


def _read_model(path: Path) -> dict[str, Any]:
    try:
        from safetensors import SafetensorError, safe_open
    except ImportError:
        raise CardError("reading the shipped models needs safetensors (pip install -e '.[train]')") from None
    params = level = 0
    dtypes: set[str] = set()
    try:
        with safe_open(str(path), framework="np") as f:
            meta = {k: (json.loads(v) if v[:1] in ("{", "[") else v) for k, v in (f.metadata() or {}).items()}
            for key in f.keys():
                piece = f.get_slice(key)
                dtypes.add(piece.get_dtype())
                if not key.endswith(BN_STATISTICS):
                    n = 1
                    for d in piece.get_shape():
                        n *= d
                    params += n
                    level += n if key.startswith("refine.") else 0
    except (OSError, SafetensorError, ValueError) as e:
        raise CardError(f"{path}: cannot read the model: {getattr(e, 'strerror', None) or e}") from None
    if not isinstance(meta.get("model"), dict) or not isinstance(meta.get("training"), dict):
        raise CardError(f"{path}: no model and training metadata")
    model = meta["model"]
    rules = meta.get("rules") or {k: model[k] for k in RULE_TEXT if k in model}
    return {"meta": meta, "rules": rules, "parameters": params, "level_parameters": level,
            "dtypes": sorted(d for d in dtypes if d.startswith(("F", "BF"))), "bytes": path.stat().st_size,
            "path": path}


def _accumulator(report: dict[str, Any], rule: str) -> Any:
    """A report's counts for ``rule`` (``model``, ``prior`` or ``oracle``) as an ``Accumulator``."""
    import numpy as np

    from fruxel.train.eval.metrics import Accumulator

    try:
        result = report["results"][rule]
    except KeyError:
        raise CardError(f"{report['_path']}: has no {rule} result") from None
    conf = np.asarray(result["confusion"], dtype=np.int64)
    acc = Accumulator(conf.shape[0])
    acc.conf = conf
    for name in COUNTS:
        setattr(acc, name, result["counts"][name])
    acc.samples = int(result["samples"])
    return acc


def _empty_like(acc: Any) -> Any:
    return type(acc)(acc.classes)


def _samples_key(report: dict[str, Any]) -> tuple[str, int, int]:
    d = report["data"]
    return str(d["split"]), int(d["seed"]), int(d["samples"])


def _summary(acc: Any, names: Sequence[str]) -> dict[str, Any]:
    return acc.summary(tuple(names))


# ---------------------------------------------------------------------------------------------------- formatting
def _num(v: float | None, decimals: int) -> str:
    return "n/a" if v is None else f"{v:,.{decimals}f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], align: str = "") -> list[str]:
    """A Markdown table; ``align`` has an ``l`` (left) or ``r`` (right) per column, default ``l`` then ``r`` s."""
    align = align or "l" + "r" * (len(header) - 1)
    marks = ["---" if a == "l" else "---:" for a in align]
    return ["| " + " | ".join(header) + " |", "| " + " | ".join(marks) + " |",
            *("| " + " | ".join(r) + " |" for r in rows)]


def _set_name(report: dict[str, Any]) -> str:
    d = report["data"]
    return f"seed {d['seed']}"


def _metric_cells(summary: dict[str, Any], bold: bool = False) -> list[str]:
    cells = [_num(summary[k], nd) for k, _, nd in METRICS]
    return [f"**{c}**" for c in cells] if bold else cells


# ---------------------------------------------------------------------------------------------------- tables
def table_models(src: Sources) -> list[str]:
    """What each shipped model is: its file, grid, input, size, training and where its rules were chosen."""
    cols = []
    for name, shipped in SHIPPED.items():
        m = src.model(name)
        model, training = m["meta"]["model"], m["meta"]["training"]
        g = model["grid"]
        h, w = _image_size(src, shipped.pool)
        names = model["classes"]["names"]
        level = f" ({m['level_parameters']:,} in the 128^3 level)" if m["level_parameters"] else ""
        cal = training.get("calibration") or {}
        seed = cal.get("seed", str(cal.get("data", "")).rpartition("seed=")[2] or "?")
        cols.append([
            f"`train/data/{shipped.file}`",
            f"{g['width']} x {g['height']} x {g['depth']} cells, z {g['z_near']:g} to {g['z_far']:g} m, "
            f"{g['hfov']:g} degrees horizontal field of view",
            f"{len(names)}: {', '.join(names)}",
            f"one {w} x {h} RGB image",
            f"{m['parameters']:,}{level}",
            f"{', '.join(_DTYPE.get(d, d) for d in m['dtypes'])}, {m['bytes'] / 1e6:.1f} MB",
            f"{training['steps']:,} steps of batch {training['batch_size']}: {training['samples_drawn']:,} samples",
            f"{training['training_seconds']:,.0f} s on {training['gpu']}",
            str(training.get("precision", "")),
            f"{cal.get('samples', 0):,} training-split samples of data seed {seed}" if cal else "n/a",
        ])
    rows = ["file", "output", "classes", "input", "parameters", "weights", "training", "GPU time", "precision",
            "inference rules chosen or checked on"]
    return _table(["", *SHIPPED], [[r, *(c[i] for c in cols)] for i, r in enumerate(rows)], "l" * (len(SHIPPED) + 1))


_DTYPE = {"F16": "float16", "BF16": "bfloat16", "F32": "float32"}


def _image_size(src: Sources, pool: Pool) -> tuple[int, int]:
    """``(h, w)`` of the images a model reads, the same in every report of its pool."""
    sizes = {tuple(src.report(n)["model"]["image_size"]) for n in pool.reports}
    if len(sizes) != 1:
        raise CardError(f"the reports of {pool.label} disagree on the image size: {sorted(sizes)}")
    return sizes.pop()


def table_architecture(src: Sources) -> list[str]:
    """The shipped sizes of each part, from the models' metadata (per-level lists run from the finest level)."""
    def row(what: str, get: Callable[[dict[str, Any]], Any]) -> list[str]:
        return [what, *(str(get(src.model(n)["meta"]["model"])) for n in SHIPPED)]

    def seq(values: Sequence[int]) -> str:
        return ", ".join(str(v) for v in values)

    rows = [
        row("2D stem, channels", lambda m: m["stem"]),
        row("detail branch (the full image), channels", lambda m: m.get("detail_branch") or "none"),
        row("2D encoder, channels per level", lambda m: seq(m["encoder"])),
        row("2D inverted residual blocks per level (expansion)",
            lambda m: f"{seq(m['encoder_blocks'])} (x{m['encoder_expand']})"),
        row("top-down path, channels per level", lambda m: seq(m["topdown"])),
        row("3D decoder, channels per level", lambda m: seq(m["decoder"])),
        row("3D inverted residual blocks per level (expansion)",
            lambda m: f"{seq(m['decoder_blocks'])} (x{m['expand']})"),
        row("128^3 refinement level, channels", lambda m: m.get("refine") or "none"),
    ]
    return _table(["part", *SHIPPED], rows)


RULE_TEXT = {
    "flip_average": "first: the image and its mirror image are predicted and the logits averaged, the mirror's "
                    "mirrored back",
    "empty_offset": "added to every cell's empty logit (the class-weighted training calls cells occupied too readily)",
    "fill_columns": "a column left empty where the depth head sees a surface gets one cell, where the volume finds "
                    "the surface most likely",
    "fill_threshold": "the depth head's \"no surface\" probability below which `fill_columns` fills a column",
    "first_hit_label": "last: each column's first occupied cell takes the class most likely to be the column's "
                       "first hit, what the camera sees",
}
"""What each inference rule does, by its key in the shipped file's metadata."""


def table_rules(src: Sources) -> list[str]:
    """The inference rules each shipped model applies after its network."""
    rules = {n: src.model(n)["rules"] for n in SHIPPED}
    keys = list(dict.fromkeys(k for r in rules.values() for k in r))

    def cell(v: Any) -> str:
        return "n/a" if v is None else ("on" if v is True else "off" if v is False else f"{v:g}")

    rows = [[f"`{k}`", *(cell(rules[n].get(k)) for n in SHIPPED), RULE_TEXT.get(k, "")] for k in keys]
    return _table(["rule", *SHIPPED, "what it does"], rows, "l" + "r" * len(SHIPPED) + "l")


def table_headline(src: Sources) -> list[str]:
    """The shipped models on their test sets against the two baselines, with the sample counts and targets."""
    header, cols = ["metric"], []
    for name, shipped in SHIPPED.items():
        names = src.report(shipped.pool.reports[0])["classes"]["names"]
        model, _ = src.pool(shipped.pool)
        oracle, _ = src.pool(shipped.pool, "oracle")
        prior_report = src.report(shipped.prior)
        if _samples_key(prior_report) not in {_samples_key(src.report(n)) for n in shipped.pool.reports} \
                or prior_report["model"]["grid"] != src.report(shipped.pool.reports[0])["model"]["grid"]:
            raise CardError(f"{prior_report['_path']}: not on {name}'s grid and test samples")
        prior = _accumulator(prior_report, "prior")
        for label, acc in ((f"**{name}**", model), ("per-cell prior", prior), ("visible-surface oracle", oracle)):
            header.append(label)
            cols.append((_summary(acc, names), acc.samples, label.startswith("**")))
    rows = [["test samples", *(f"{n:,}" for _, n, _ in cols), ""]]
    for key, title, nd in METRICS:
        rows.append([title, *(f"**{_num(s[key], nd)}**" if b else _num(s[key], nd) for s, _, b in cols),
                     TARGETS.get(key, "")])
    return _table([*header, "target"], rows)


def table_sets(src: Sources, name: str) -> list[str]:
    """One shipped model per test set, all sets together, and how much the sets differ."""
    import numpy as np

    shipped = SHIPPED[name]
    total, sets = src.pool(shipped.pool)
    names = src.report(shipped.pool.reports[0])["classes"]["names"]
    rows = []
    for report, acc in sets:
        rows.append([_set_name(report), f"{acc.samples:,}", f"{acc.samples // SAMPLES_PER_ROOM:,}",
                     *_metric_cells(_summary(acc, names))])
    for file, what in shipped.extra:
        report = src.report(file)
        acc = _accumulator(report, "model")
        rows.append([what, f"{acc.samples:,}", f"{acc.samples // SAMPLES_PER_ROOM:,}",
                     *_metric_cells(_summary(acc, names))])
    rows.append(["**all sets together**", f"**{total.samples:,}**", f"**{total.samples // SAMPLES_PER_ROOM:,}**",
                 *_metric_cells(_summary(total, names), bold=True)])
    size = max({a.samples for _, a in sets}, key=lambda n: sum(a.samples == n for _, a in sets))
    alike = [_summary(a, names) for _, a in sets if a.samples == size]
    if len(alike) >= 3:
        sd = {k: float(np.std([s[k] for s in alike], ddof=1)) for k, _, _ in METRICS}
        se = (size / total.samples) ** 0.5
        rows.append([f"standard deviation between the {len(alike)} sets of {size:,}", "", "",
                     *(_num(sd[k], nd) for k, _, nd in METRICS)])
        rows.append(["standard error of all sets together, from it", "", "",
                     *(_num(sd[k] * se, nd) for k, _, nd in METRICS)])
    return _table(["test set", "samples", "rooms", *(t for _, t, _ in METRICS)], rows)


def table_classes(src: Sources) -> list[str]:
    """IoU per class of each shipped model and the oracle over its test sets, with each class's share of cells."""
    header, cols, share = ["class"], [], None
    names: Sequence[str] = ()
    for name, shipped in SHIPPED.items():
        names = src.report(shipped.pool.reports[0])["classes"]["names"]
        model, _ = src.pool(shipped.pool)
        oracle, _ = src.pool(shipped.pool, "oracle")
        if share is None:
            truth = model.conf.sum(axis=1)
            share = (f"share of {name}'s test cells (%)", 100.0 * truth / truth.sum())
        header += [f"{name} ({model.samples:,})", "oracle"]
        cols += [_summary(model, names)["iou"], _summary(oracle, names)["iou"]]
    assert share is not None
    rows = [[c, f"{share[1][i]:.2f}", *(_num(col[c], 1) for col in cols)] for i, c in enumerate(names) if i]
    return _table([header[0], share[0], *header[1:]], rows)


def _pools_table(src: Sources, pools: Sequence[Pool], reference: Pool) -> list[str]:
    """Several models on the same test sets as ``reference`` (checked), counted together."""
    want = sorted(_samples_key(src.report(n)) for n in reference.reports)
    rows = []
    for pool in pools:
        got = sorted(_samples_key(src.report(n)) for n in pool.reports)
        if got != want:
            raise CardError(f"{pool.label}: its reports ({', '.join(pool.reports)}) are not on {reference.label}'s "
                            "test samples")
        total, _ = src.pool(pool)
        names = src.report(pool.reports[0])["classes"]["names"]
        bold = pool is reference
        h, w = _image_size(src, pool)
        rows.append([f"**{pool.label}**" if bold else pool.label, pool.about.format(image=f"{w} x {h}"),
                     *_metric_cells(_summary(total, names), bold)])
    return _table(["model", "what it is", *(t for _, t, _ in METRICS)], rows, "ll" + "r" * len(METRICS))


def table_candidates(src: Sources) -> list[str]:
    """The 64^3 models measured on ssz64's test sets."""
    return _pools_table(src, CANDIDATES, SHIPPED["ssz64"].pool)


def table_level(src: Sources) -> list[str]:
    """The 128^3 models on the same first 1,024 test samples."""
    return _pools_table(src, LEVEL, LEVEL[0])


def table_camera_models(src: Sources) -> list[str]:
    """What each camera-aware model is, from its metadata: file, output, classes, inputs, size, training (all its
    runs, from the model it started from) and inference rules."""
    rows = []
    for name, shipped in CAMERA_AWARE.items():
        m = src.model(name)
        model, training = m["meta"]["model"], m["meta"]["training"]
        g, (h, w) = model["grid"], src.report(shipped.reports[0])["model"]["image_size"]
        on = [k for k, v in m["rules"].items() if v is True]
        offset = m["rules"].get("empty_offset")
        rules = ", ".join(on + ([f"empty offset {offset:g}"] if offset else [])) or "none"
        rows.append([f"`{name}`", f"`train/data/{shipped.file}`",
                     f"{g['width']} x {g['height']} x {g['depth']} cells, z {g['z_near']:g} to {g['z_far']:g} m",
                     ", ".join(model["classes"]["names"]),
                     f"one {w} x {h} RGB image; gravity and height, each optional",
                     f"{m['parameters']:,}", f"{m['bytes'] / 1e6:.1f} MB",
                     f"{training['steps']:,} steps of batch {training['batch_size']}, from "
                     f"`{training.get('init', '')}`",
                     rules])
    return _table(["model", "file", "output", "classes", "input", "parameters", "weights", "training",
                   "inference rules"], rows, "l" * 9)


def camera_results(src: Sources, name: str) -> Iterator[tuple[dict[str, Any], str, str, str, Any]]:
    """Each result of a camera-aware model's reports, in their order: ``(report, test set, result key, its name in
    the tables, accumulator)``."""
    from fruxel.train.eval.report import rule_names

    for file in CAMERA_AWARE[name].reports:
        report = src.report(file)
        test_set = (report["data"].get("test_set") or {}).get("name", "?")
        for key, label in rule_names(report).items():
            yield report, test_set, key, label, _accumulator(report, key)


def table_camera_sets(src: Sources, name: str) -> list[str]:
    """A camera-aware model on each of its test sets, under each camera setting, beside the visible-surface
    oracle."""
    rows = [[f"`{test_set}`", label, f"{acc.samples:,}", *_metric_cells(_summary(acc, report["classes"]["names"]))]
            for report, test_set, key, label, acc in camera_results(src, name) if key != "prior"]
    return _table(["test set", "prediction", "samples", *(t for _, t, _ in METRICS)], rows, "ll" + "r" * 6)


TABLES: dict[str, Callable[[Sources], list[str]]] = {
    "models": table_models,
    "architecture": table_architecture,
    "rules": table_rules,
    "headline": table_headline,
    **{f"sets-{n}": (lambda src, n=n: table_sets(src, n)) for n in SHIPPED},
    "classes": table_classes,
    "candidates": table_candidates,
    "level": table_level,
    "camera-models": table_camera_models,
    **{f"camera-sets-{n}": (lambda src, n=n: table_camera_sets(src, n)) for n in CAMERA_AWARE},
}
"""Every generated table of the card by its marker name."""


def table_results(src: Sources) -> list[str]:
    """The README's short table: the default, camera-aware model on each of its test sets under each camera
    setting, then each robot-mount model's headline numbers on its pooled test sets (the flat world's ``robot``
    samples)."""
    rows = [_results_row(name, report["model"]["grid"], f"`{test_set}`, {label.removeprefix('model, ')}",
                         _summary(acc, report["classes"]["names"]), acc.samples)
            for name in CAMERA_AWARE for report, test_set, key, label, acc in camera_results(src, name)
            if key.startswith("model")]
    for name, shipped in SHIPPED.items():
        acc, _ = src.pool(shipped.pool)
        report = src.report(shipped.pool.reports[0])
        rows.append(_results_row(name, report["model"]["grid"], "`robot`", _summary(acc, report["classes"]["names"]),
                                 acc.samples))
    return _table(["model", "cells", "test set", "test samples", *(t for _, t, _ in METRICS[:4])], rows,
                  "lll" + "r" * 5)


def _results_row(name: str, grid: dict[str, Any], test_set: str, s: dict[str, Any], samples: int) -> list[str]:
    """One row of :func:`table_results`."""
    return [f"`{name}`", f"{grid['width']}x{grid['height']}x{grid['depth']}", test_set, f"{samples:,}",
            *(_num(s[k], nd) for k, _, nd in METRICS[:4])]


README_TABLES: dict[str, Callable[[Sources], list[str]]] = {"results": table_results}
"""Every generated table of the README by its marker name."""


# ---------------------------------------------------------------------------------------------------- the card
def render(card: str, path: Path, src: Sources,
           tables: dict[str, Callable[[Sources], list[str]]] = TABLES) -> tuple[str, list[str]]:
    """The card with every generated table made again.

    Args:
        card: the card's text.
        path: its file (for error messages).
        src: where the tables read.

    Returns:
        The new text and the names of the tables whose text changed.

    Raises:
        CardError: a marker that is unknown, repeated, nested or not closed, or a table of :data:`TABLES` the card
            lacks; and whatever the tables raise.
    """
    out: list[str] = []
    changed: list[str] = []
    seen: set[str] = set()
    lines = card.split("\n")
    i = 0
    while i < len(lines):
        line = lines[i]
        out.append(line)
        m = START.match(line)
        i += 1
        if not m:
            if line.startswith("<!-- generated") or line == END:
                raise CardError(f"{path}:{i}: a marker out of place or misspelt: {line!r}")
            continue
        name = m.group(1)
        if name not in tables:
            raise CardError(f"{path}:{i}: no generated table is called {name!r} (known: {', '.join(tables)})")
        if name in seen:
            raise CardError(f"{path}:{i}: the table {name!r} appears twice")
        seen.add(name)
        start = i
        while i < len(lines) and lines[i] != END:
            if START.match(lines[i]):
                raise CardError(f"{path}:{i + 1}: a table opens inside {name!r} (line {start}) before its {END}")
            i += 1
        if i == len(lines):
            raise CardError(f"{path}:{start}: the table {name!r} has no {END} line")
        # A blank line before the end marker ends the table for every Markdown reader (GFM tables run on over
        # lines that are not blank).
        body = [*tables[name](src), ""]
        if lines[start:i] != body:
            changed.append(name)
        out += [*body, END]
        i += 1
    missing = [n for n in tables if n not in seen]
    if missing:
        raise CardError(f"{path}: has no generated table {', '.join(missing)} (add <!-- generated: NAME --> and "
                        f"{END} lines where it belongs)")
    return "\n".join(out), changed


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="model_card.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--check", action="store_true",
                   help="write nothing; exit with status 1 and name the tables when the card is out of date")
    p.add_argument("--card", type=Path, default=ROOT / "docs" / "model.md", help="the card (default: docs/model.md)")
    p.add_argument("--readme", type=Path, default=ROOT / "README.md",
                   help="the README, whose short results table is generated too (default: README.md)")
    p.add_argument("--reports", type=Path, default=ROOT / "docs" / "eval",
                   help="the folder of the fruxel-eval reports (default: docs/eval)")
    p.add_argument("--models", type=Path, default=ROOT / "train" / "data",
                   help="the folder of the shipped models (default: train/data)")
    return p


def _main(args: argparse.Namespace) -> int:
    src = Sources(args.reports, args.models)
    pages = []
    for path, tables in ((args.card, TABLES), (args.readme, README_TABLES)):
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise CardError(f"{path}: cannot read it: {getattr(e, 'strerror', None) or e}") from None
        pages.append((path, *render(text, path, src, tables)))
    if args.check:
        stale = [f"{path}: out of date: {', '.join(changed)}" for path, _, changed in pages if changed]
        for line in stale:
            print(f"{line} (run python scripts/model_card.py)", file=sys.stderr)
        for path, _, changed in pages:
            if not changed:
                print(f"{path}: up to date")
        return 1 if stale else 0
    write_outputs([(path, lambda tmp, text=text: tmp.write_text(text, encoding="utf-8"))
                   for path, text, changed in pages if changed])
    for path, _, changed in pages:
        print(f"{path}: {', '.join(changed) + ' rewritten' if changed else 'up to date'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run(_main, _parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
