"""The evaluation report of ``fruxel-eval``: a model against the two baselines of conventions section 9 on the same
samples.

:func:`build_report` gathers the counts of each prediction rule (:class:`~.metrics.Accumulator`) and what was
evaluated into one JSON-able dict (``report.json``); :func:`markdown_report` writes that dict as Markdown
(``report.md``), so the Markdown can always be made again from the JSON.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from fruxel.classes import ClassTable

from .metrics import Accumulator

FORMAT = "fruxel-eval-report"
"""``format`` of ``report.json``."""
VERSION = 1
"""Version of ``report.json``'s layout."""
RULES = {"model": "model", "prior": "per-cell prior", "oracle": "visible-surface oracle"}
"""The prediction rules of a report, by key, and their names in the tables."""
SETTING = "model@"
"""Key prefix of the model under a further ``--camera-known`` setting (``model@none``, ``model@gravity``): the first
setting's results are ``model``'s, as the report's ``data.camera_known`` says."""


def setting_text(pieces: Any) -> str:
    """A camera-known setting (a list of :data:`fruxel.train.models.conditioning.KNOWN` pieces) as the command line
    writes it: ``gravity,height``, ``gravity`` or ``none``."""
    return ",".join(pieces) or "none"


def setting_key(pieces: Any) -> str:
    """The results key of the model told ``pieces`` of the camera, when that is not its first setting."""
    return SETTING + setting_text(pieces)


def rule_names(report: Mapping[str, Any]) -> dict[str, str]:
    """The name in the tables of each rule of a report's results, in their order: :data:`RULES`, and for a model
    that reads the camera (the report's ``data.camera_known`` is set), ``model, camera known: <setting>``."""
    keys = list(report["results"])
    # Reports written before camera settings existed have no camera_known: their model reads no camera.
    known = report["data"].get("camera_known")

    def name(key: str) -> str:
        if key.startswith(SETTING):
            return f"model, camera known: {key[len(SETTING):]}"
        if key == "model" and known is not None:
            return f"model, camera known: {setting_text(known)}"
        return RULES[key]

    return {k: name(k) for k in keys}
METRICS = (
    ("miou", "mIoU", "%"),
    ("completion_iou", "completion IoU", "%"),
    ("own_view_accuracy", "own-view first-hit accuracy", "%"),
    ("novel_view_accuracy", "novel-view first-hit accuracy", "%"),
    ("depth_error", "novel-view depth error", "m"),
)
"""``(key of Accumulator.summary, name, unit)`` of the summary table's rows."""
DEFINITIONS = {
    "prior": "every cell gets its most frequent label over the training samples counted (ties go to the lower class "
             "id, empty first), the same volume for every sample: where things usually are, without the image.",
    "oracle": "the ground truth's own-view shell alone: the first occupied cell of each column with its true label, "
              "nothing behind it; a perfect depth and segmentation network that completes nothing.",
}
"""What each baseline predicts, in words (written into the report)."""


def rule_result(acc: Accumulator, classes: ClassTable) -> dict[str, Any]:
    """One rule's metrics (:meth:`Accumulator.summary`) with the counts behind them.

    Returns:
        The summary's keys, plus ``confusion`` (``C x C`` cell counts ``[true][predicted]``) and ``counts`` (the
        own- and novel-view pixel counts and the summed depth error).
    """
    out = acc.summary(tuple(classes.names))
    out["confusion"] = np.asarray(acc.conf, dtype=np.int64).tolist()
    out["counts"] = {k: getattr(acc, k) for k in ("own_hits", "own_correct", "novel_pixels", "novel_correct",
                                                     "depth_pixels", "depth_abs_sum")}
    return out


def build_report(results: Mapping[str, Accumulator], classes: ClassTable, *, model: dict[str, Any],
                 data: dict[str, Any], prior: dict[str, Any] | None, machine: dict[str, Any], command: str,
                 seconds: float, examples: str | None = "examples.png",
                 by_camera: dict[str, Any] | None = None) -> dict[str, Any]:
    """The report as a JSON-able dict (``report.json``).

    Args:
        results: the accumulators by rule, keys from :data:`RULES` (``"model"`` first; a baseline not evaluated is
            left out) and :func:`setting_key` (the model under further camera-known settings, after ``"model"``).
        classes: the class table of the labels.
        model: the model: ``file``, ``grid`` (a grid dict), ``image_size`` ``[h, w]``, ``training`` (its summary),
            optionally ``inference_rules`` (``{"fill_columns": bool, "empty_offset": float, "fill_threshold":
            float, "first_hit_label": bool, "flip_average": bool}``).
        data: the samples: ``source`` (in words), ``split``, ``samples``, optionally ``test_set`` (``{"name",
            "description"}`` of a held-out test set, :data:`fruxel.train.sim.testsets.TEST_SETS`), and anything else
            worth keeping.
        prior: how the per-cell prior was made (``split``, ``samples``), None when it was not.
        machine: where it ran (CPU, GPU, versions, device, kernel backend).
        command: the command line.
        seconds: wall time of the evaluation.
        examples: the picture of examples beside the report, or None.
        by_camera: the metrics per camera height and pitch bin
            (:func:`fruxel.train.eval.by_camera.by_camera_section`), or None.
    """
    names = tuple(classes.names)
    truth = next(iter(results.values())).conf.sum(axis=1) if results else np.zeros(len(names))
    total = float(truth.sum())
    share = {names[c]: (100.0 * float(truth[c]) / total if total else None) for c in range(len(names))}
    return {
        "format": FORMAT,
        "version": VERSION,
        "command": command,
        "model": model,
        "data": data,
        "prior": prior,
        "machine": machine,
        "seconds": round(float(seconds), 2),
        "classes": classes.to_dict(),
        "class_share": share,
        "results": {name: rule_result(acc, classes) for name, acc in results.items()},
        "definitions": {k: v for k, v in DEFINITIONS.items() if k in results},
        "examples": examples,
        "by_camera": by_camera,
    }


def _value(v: Any, unit: str, digits: int = 1) -> str:
    if v is None:
        return "n/a"
    return f"{v:.3f}" if unit == "m" else f"{v:.{digits}f}"


def _table(header: list[str], rows: list[list[str]], numbers: bool = True) -> list[str]:
    """A Markdown table; with ``numbers`` every column but the first is right-aligned."""
    align = ["---"] + ["---:" if numbers else "---"] * (len(header) - 1)
    return ["| " + " | ".join(header) + " |", "| " + " | ".join(align) + " |",
            *("| " + " | ".join(r) + " |" for r in rows)]


def _grid_text(g: Mapping[str, Any]) -> str:
    return (f"{g['width']}x{g['height']}x{g['depth']} cells, z {g['z_near']:g}..{g['z_far']:g} m, "
            f"hfov {g['hfov']:g} deg")


def _plain(d: Mapping[str, Any], skip: tuple[str, ...] = ()) -> str:
    """The scalar entries of a dict as ``key value, ...``."""
    parts = []
    for k, v in d.items():
        if k in skip or isinstance(v, (dict, list, tuple)) or v is None:
            continue
        parts.append(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}")
    return ", ".join(parts)


def rules_text(rules: Mapping[str, Any]) -> str:
    """The model's inference rules (``ModelConfig.flip_average``, ``fill_columns``, ``empty_offset``,
    ``fill_threshold``, ``first_hit_label``) in words."""
    parts = ["flip_average"] if rules.get("flip_average") else []
    if rules.get("empty_offset"):
        parts.append(f"empty logit {rules['empty_offset']:+g}")
    if rules.get("fill_columns"):
        t = rules.get("fill_threshold")
        parts.append("fill_columns" + (f" (threshold {t:g})" if t is not None else ""))
    if rules.get("first_hit_label"):
        parts.append("first_hit_label")
    return ", ".join(parts) or "none (plain argmax)"


def markdown_report(report: Mapping[str, Any]) -> str:
    """``report.md``: the report of :func:`build_report` as Markdown (a summary, then the tables)."""
    names = rule_names(report)
    rules = list(names)
    res = report["results"]
    m, d = report["model"], report["data"]
    head = [f"# Evaluation of {m['file']}", ""]
    trained = _plain(m.get("training") or {})
    h, w = m["image_size"]
    about = [
        ["model", f"`{m['file']}`: grid {_grid_text(m['grid'])}, {w}x{h} images, {len(report['classes']['names'])} "
                  f"classes" + (f"; inference rules: {rules_text(m['inference_rules'])}" if "inference_rules" in m
                                else "") + (f"; trained: {trained}" if trained else "")],
        ["samples", f"{d['samples']} samples of split `{d['split']}` ({d.get('indices', '')}), {d['source']}"],
    ]
    if d.get("test_set"):
        about.append(["test set", f"`{d['test_set']['name']}`: {d['test_set']['description']}"])
    if report.get("prior"):
        p = report["prior"]
        about.append(["per-cell prior", f"mode of {p['samples']} samples of split `{p['split']}` of the same source"])
    mach = report["machine"]
    about.append(["machine", _plain(mach)])
    about.append(["time", f"{report['seconds']:g} s"])
    about.append(["command", f"`{report['command']}`"])
    lines = head + _table(["", ""], about, numbers=False)

    lines += ["", "## Metrics", ""]
    rows = [[f"{name} ({unit})"] + [_value(res[r].get(key), unit) for r in rules] for key, name, unit in METRICS]
    lines += _table(["metric", *names.values()], rows)
    lines += ["", "mIoU: the mean IoU over the classes present in the ground truth; IoU, accuracy and depth error are "
                  "counted over every cell or pixel of every sample together. Novel views: "
                  "`orbit_cameras(grid, 4)` at the grid's width and height; accuracy over the pixels where either "
                  "volume is hit, depth error where both are."]

    lines += ["", "## IoU per class (%)", ""]
    classes = report["classes"]["names"]
    share = report["class_share"]
    # Shares with two decimals: small classes hold a few hundredths of the cells.
    rows = [[name, _value(share.get(name), "%", 2)] + [_value(res[r]["iou"].get(name), "%") for r in rules]
            for name in classes[1:]]
    lines += _table(["class", "share of cells", *names.values()], rows)
    lines += ["", f"Empty cells: {_value(share.get(classes[0]), '%')} % of the ground truth. n/a: a class neither in "
                  "the ground truth nor predicted."]
    if report.get("by_camera"):
        lines += _by_camera_lines(report["by_camera"], names)

    defs = report.get("definitions") or {}
    if defs:
        lines += ["", "## Baselines", ""]
        lines += [f"- **{RULES[k]}**: {v}" for k, v in defs.items()]
    if report.get("examples"):
        lines += ["", "## Examples", "",
                  "Per sample: the image | truth and model prediction from the grid's own camera | truth and model "
                  "prediction ray-cast from a novel pose.", "", f"![examples]({report['examples']})"]
    return "\n".join(lines) + "\n"


def _by_camera_lines(section: Mapping[str, Any], names: Mapping[str, str]) -> list[str]:
    """The Markdown of a report's ``by_camera`` section: a table per axis, then the chart."""
    from .by_camera import AXES

    lines = ["", "## By camera", "",
             "mIoU and own-view first-hit accuracy (%) of the samples whose camera lies in each bin, counted as the "
             "overall metrics are; a bin is [low, high), the last one closed."]
    for axis, (unit, words) in AXES.items():
        part = section[axis]
        rules = list(part["miou"])
        header = [f"{words} ({unit})", "samples"] + [f"{what}, {names.get(r, r)}" for r in rules
                                                     for what in ("mIoU", "own-view")]
        edges = part["edges"]
        rows = [[f"{lo:g}..{hi:g}", str(n)] + [_value(part[key][r][i], "%") for r in rules
                                             for key in ("miou", "own_view_accuracy")]
                for i, (lo, hi, n) in enumerate(zip(edges, edges[1:], part["samples"], strict=False))]
        lines += ["", *_table(header, rows)]
        out = part["outside"]
        if any(out.values()):
            lines += ["", "Samples in no bin: " + ", ".join(f"{n} {k}" for k, n in out.items() if n) + "."]
    if section.get("chart"):
        lines += ["", f"![by camera]({section['chart']})"]
    return lines
