"""Tables of the evaluation: the ``metrics.json`` schema, assembling steps into a table,
reading and writing it (JSON, CSV, Markdown), aggregating seeds and sweeps."""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np

from chisel.core.atomic import atomic_write_text, atomic_write_texts
from chisel.core.errors import InvalidInputError
from chisel.io.limits import read_text_limited
from chisel.io.manifest import read_json_manifest

METHODS: tuple[str, ...] = ("no_update", "updated", "depth_ablation", "registration_ablation")
"""The paper's methods, in table order. Other method names are allowed and sort after these."""

METRICS_FORMAT = "endoscopic-chisel/metrics"
STEP_METRICS_FORMAT = "endoscopic-chisel/step-metrics"
SEED_METRICS_FORMAT = "endoscopic-chisel/metrics-seeds"
METRICS_VERSION = 1

METRIC_KEYS: tuple[str, ...] = (
    "mean_mm",
    "std_mm",
    "median_mm",
    "n_points",
    "n_gt_in_box",
    "missing_fraction",
    "accuracy_mm",
    "completeness_mm",
    "accuracy_hd95_mm",
    "completeness_hd95_mm",
    "hd95_mm",
    "chamfer_mm",
    "precision_1mm",
    "recall_1mm",
    "fscore_1mm",
    "mask_precision",
    "mask_recall",
    "removed_dice",
    "removed_hd95_mm",
    "removed_precision",
    "removed_recall",
)
"""Every key of a method's cell in ``metrics.json``; a value is a number or null."""
OPTIONAL_KEYS: tuple[str, ...] = (
    "removed_dice",
    "removed_hd95_mm",
    "removed_precision",
    "removed_recall",
)
"""Keys a cell may lack (tables written before the volumetric scores, or before their
precision and recall, existed): read as null."""

_NUM_OR_NULL = {"type": ["number", "null"]}
_METHOD_CELL_SCHEMA = {
    "type": "object",
    "required": [k for k in METRIC_KEYS if k not in OPTIONAL_KEYS],
    "properties": {
        **{k: _NUM_OR_NULL for k in METRIC_KEYS},
        "n_points": {"type": "integer", "minimum": 1},
        "n_gt_in_box": {"type": "integer", "minimum": 1},
        "mean_mm": {"type": "number", "minimum": 0},
        "std_mm": {"type": "number", "minimum": 0},
    },
}
_STEP_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["step", "label", "methods"],
    "properties": {
        "step": {"type": "integer", "minimum": 0},
        "label": {"type": "string"},
        "methods": {
            "type": "object",
            "minProperties": 1,
            "additionalProperties": _METHOD_CELL_SCHEMA,
        },
    },
}
METRICS_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "metrics.json: evaluation of one experiment (rows = steps, columns = methods)",
    "type": "object",
    "required": ["format", "version", "experiment", "steps"],
    "properties": {
        "format": {"const": METRICS_FORMAT},
        "version": {"const": METRICS_VERSION},
        "experiment": {"type": "string"},
        "protocol": {"type": "object"},
        "steps": {"type": "array", "minItems": 1, "items": _STEP_SCHEMA},
    },
}
"""JSON schema of ``metrics.json`` (validated on write and on read)."""

STEP_METRICS_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "step_metrics.json: evaluation of one surgical step",
    "type": "object",
    "required": ["format", "version", "step", "label", "methods"],
    "properties": {
        "format": {"const": STEP_METRICS_FORMAT},
        "version": {"const": METRICS_VERSION},
        **_STEP_SCHEMA["properties"],
        "protocol": {"type": "object"},
    },
}
"""JSON schema of one step's metrics (what ``chisel evaluate`` writes)."""


# --------------------------------------------------------------------------------------
# The ROI box


def step_label(step: int) -> str:
    """``"preop"`` for step 0, ``"bite N"`` otherwise (the paper's row names)."""
    return "preop" if step == 0 else f"bite {step}"


def _method_order(names: set[str] | Sequence[str]) -> list[str]:
    known = [m for m in METHODS if m in names]
    return known + sorted(set(names) - set(METHODS))


def validate_step_metrics(d: Mapping[str, Any], source: str = "step metrics") -> None:
    """Raise :class:`InvalidInputError` if ``d`` does not follow ``STEP_METRICS_SCHEMA``."""
    try:
        jsonschema.validate(d, STEP_METRICS_SCHEMA)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise InvalidInputError(
            source, f"not a step-metrics file: at {where}: {exc.message}"
        ) from None


def validate_metrics(d: Mapping[str, Any], source: str = "metrics") -> None:
    """Raise :class:`InvalidInputError` if ``d`` does not follow ``METRICS_SCHEMA``."""
    try:
        jsonschema.validate(d, METRICS_SCHEMA)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise InvalidInputError(source, f"not a metrics.json: at {where}: {exc.message}") from None
    steps = [s["step"] for s in d["steps"]]
    if len(set(steps)) != len(steps):
        raise InvalidInputError(source, f"duplicate steps {steps}")


def assemble_table(step_results: Sequence[Mapping[str, Any]], experiment: str) -> dict[str, Any]:
    """Combine per-step results into ``metrics.json`` (rows = steps, sorted).

    step_results : step dicts as returned by :func:`evaluate_step` (or ``evaluate_methods``).
    """
    if not step_results:
        raise InvalidInputError("step_results", "no step to tabulate")
    steps: dict[int, dict[str, Any]] = {}
    protocol: dict[str, Any] | None = None
    for i, r in enumerate(step_results):
        if "format" in r:
            validate_step_metrics(r, f"step_results[{i}]")
        s = int(r["step"])
        if s in steps:
            raise InvalidInputError(f"step_results[{i}]", f"step {s} appears twice")
        order = _method_order(list(r["methods"]))
        steps[s] = {
            "step": s,
            "label": step_label(s),
            "methods": {m: dict(r["methods"][m]) for m in order},
        }
        if protocol is None and "protocol" in r:
            protocol = {k: v for k, v in r["protocol"].items() if k != "eval_poses"}
    table = {
        "format": METRICS_FORMAT,
        "version": METRICS_VERSION,
        "experiment": str(experiment),
        "protocol": protocol or {},
        "steps": [steps[s] for s in sorted(steps)],
    }
    validate_metrics(table, "assembled table")
    return table


def _json_text(d: Mapping[str, Any]) -> str:
    return json.dumps(d, indent=2, allow_nan=False) + "\n"


def read_json(path: str | Path, what: str) -> dict[str, Any]:
    """Read a JSON object through :func:`chisel.io.manifest.read_json_manifest` (size and
    nesting bounded); every problem is an :class:`InvalidInputError` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, f"{what} file is missing")
    return read_json_manifest(path)


def read_metrics(path: str | Path) -> dict[str, Any]:
    """Read and validate a ``metrics.json``."""
    d = read_json(path, "metrics")
    validate_metrics(d, str(path))
    return d


def read_step_metrics(path: str | Path) -> dict[str, Any]:
    """Read and validate a ``step_metrics.json``."""
    d = read_json(path, "step metrics")
    validate_step_metrics(d, str(path))
    return d


def write_step_metrics(path: str | Path, d: Mapping[str, Any]) -> None:
    """Validate and write one step's metrics as JSON (atomically)."""
    validate_step_metrics(d, str(path))
    atomic_write_text(path, _json_text(d))


def _fmt(x: Any, digits: int = 3) -> str:
    if x is None:
        return "-"
    if isinstance(x, int):
        return str(x)
    return f"{x:.{digits}f}"


def table_methods(metrics: Mapping[str, Any]) -> list[str]:
    """Every method of a ``metrics.json``, in table order."""
    names: set[str] = set()
    for s in metrics["steps"]:
        names |= set(s["methods"])
    return _method_order(names)


def metrics_to_csv(metrics: Mapping[str, Any]) -> str:
    """Long-format CSV: one row per (step, method), every metric a column; empty = null."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["step", "label", "method", *METRIC_KEYS])
    for s in metrics["steps"]:
        for m in _method_order(list(s["methods"])):
            cell = s["methods"][m]
            w.writerow(
                [
                    s["step"],
                    s["label"],
                    m,
                    *("" if cell.get(k) is None else repr(cell[k]) for k in METRIC_KEYS),
                ]
            )
    return buf.getvalue()


def _step_method_grid(
    steps: Sequence[Mapping[str, Any]],
    methods: list[str],
    cell: Callable[[Mapping[str, Any]], str],
) -> list[str]:
    """Markdown lines of a step x method table; ``cell`` formats a method's entry of a
    step, "-" where the step has none."""
    lines = ["| step | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for s in steps:
        cells = ["-" if s["methods"].get(m) is None else cell(s["methods"][m]) for m in methods]
        lines.append(f"| {s['label']} | " + " | ".join(cells) + " |")
    return lines


def metrics_to_markdown(metrics: Mapping[str, Any]) -> str:
    """Two Markdown tables: the paper's (mean ± std (n) per step x method) and surface metrics."""
    methods = table_methods(metrics)
    lines = [f"# Evaluation: {metrics['experiment']}", ""]
    lines += [
        "Correspondence error, mm: mean ± std (n points) of same-pixel distances inside the ROI box.",
        "",
    ]
    lines += _step_method_grid(
        metrics["steps"],
        methods,
        lambda c: f"{c['mean_mm']:.3f} ± {c['std_mm']:.3f} (n={c['n_points']})",
    )
    surf_keys = (
        "accuracy_mm",
        "completeness_mm",
        "hd95_mm",
        "chamfer_mm",
        "fscore_1mm",
        "missing_fraction",
        "mask_precision",
        "mask_recall",
        "removed_dice",
        "removed_hd95_mm",
        "removed_precision",
        "removed_recall",
    )
    lines += [
        "",
        "Surface metrics inside the ROI box (mm; F-score at 1 mm; mask scores vs what each "
        "model lacked, along the masks' rays).",
        "",
        "| step | method | " + " | ".join(surf_keys) + " |",
        "|---|---|" + "---|" * len(surf_keys),
    ]
    for s in metrics["steps"]:
        for m in _method_order(list(s["methods"])):
            c = s["methods"][m]
            lines.append(
                f"| {s['label']} | {m} | " + " | ".join(_fmt(c.get(k)) for k in surf_keys) + " |"
            )
    return "\n".join(lines) + "\n"


def write_table(out_dir: str | Path, metrics: Mapping[str, Any]) -> dict[str, Path]:
    """Write ``metrics.json``, ``.csv`` and ``.md`` into ``out_dir``, all three or none
    (atomically, together); returns the paths by kind (``json``, ``csv``, ``md``)."""
    validate_metrics(metrics, "metrics")
    out = Path(out_dir)
    paths = {"json": out / "metrics.json", "csv": out / "metrics.csv", "md": out / "metrics.md"}
    texts = (_json_text(metrics), metrics_to_csv(metrics), metrics_to_markdown(metrics))
    atomic_write_texts(dict(zip(paths.values(), texts, strict=True)))
    return paths


# --------------------------------------------------------------------------------------
# Across seeds


def aggregate_seeds(
    tables: Sequence[Mapping[str, Any]], labels: Sequence[str] | None = None
) -> dict[str, Any]:
    """Mean and spread of every metric per (step, method) across several ``metrics.json``.

    tables : one ``metrics.json`` dict per seed (same experiment design).
    labels : a name per table (e.g. ``"seed 0"``), stored in the result.
    Each metric becomes ``{"mean", "std" (population, ddof=0), "min", "max", "n"}`` over
    the tables where it is not null; a metric null everywhere stays null.
    """
    if not tables:
        raise InvalidInputError("tables", "no metrics to aggregate")
    if labels is not None and len(labels) != len(tables):
        raise InvalidInputError("labels", f"{len(labels)} labels for {len(tables)} tables")
    for i, t in enumerate(tables):
        validate_metrics(t, f"tables[{i}]")
    values: dict[int, dict[str, dict[str, list[float]]]] = {}
    for t in tables:
        for s in t["steps"]:
            per_method = values.setdefault(int(s["step"]), {})
            for m, cell in s["methods"].items():
                per_key = per_method.setdefault(m, {k: [] for k in METRIC_KEYS})
                for k in METRIC_KEYS:
                    if cell.get(k) is not None:
                        per_key[k].append(float(cell[k]))
    steps = []
    for s in sorted(values):
        methods = {}
        for m in _method_order(list(values[s])):
            agg: dict[str, Any] = {}
            for k, vals in values[s][m].items():
                if not vals:
                    agg[k] = None
                    continue
                a = np.asarray(vals)
                agg[k] = {
                    "mean": float(a.mean()),
                    "std": float(a.std()),
                    "min": float(a.min()),
                    "max": float(a.max()),
                    "n": int(a.size),
                }
            methods[m] = agg
        steps.append({"step": s, "label": step_label(s), "methods": methods})
    return {
        "format": SEED_METRICS_FORMAT,
        "version": METRICS_VERSION,
        "experiment": str(tables[0]["experiment"]),
        "inputs": list(labels)
        if labels is not None
        else [f"input {i}" for i in range(len(tables))],
        "steps": steps,
    }


def seeds_to_csv(agg: Mapping[str, Any]) -> str:
    """Long-format CSV of :func:`aggregate_seeds`: step, label, method, metric, mean, std, min, max, n."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["step", "label", "method", "metric", "mean", "std", "min", "max", "n"])
    for s in agg["steps"]:
        for m, cell in s["methods"].items():
            for k in METRIC_KEYS:
                v = cell[k]
                if v is None:
                    w.writerow([s["step"], s["label"], m, k, "", "", "", "", 0])
                else:
                    w.writerow(
                        [
                            s["step"],
                            s["label"],
                            m,
                            k,
                            repr(v["mean"]),
                            repr(v["std"]),
                            repr(v["min"]),
                            repr(v["max"]),
                            v["n"],
                        ]
                    )
    return buf.getvalue()


def seeds_to_markdown(agg: Mapping[str, Any]) -> str:
    """Markdown: the correspondence error per step x method, mean ± std across inputs."""
    methods = table_methods(agg)
    lines = [
        f"# Evaluation across {len(agg['inputs'])} runs: {agg['experiment']}",
        "",
        "Correspondence error, mm: mean over runs of the per-run mean ± std over runs (runs).",
        "",
    ]

    def cell(c: Mapping[str, Any]) -> str:
        v = c["mean_mm"]
        return "-" if v is None else f"{v['mean']:.3f} ± {v['std']:.3f} ({v['n']})"

    lines += _step_method_grid(agg["steps"], methods, cell)
    return "\n".join(lines) + "\n"


def write_seed_table(out_dir: str | Path, agg: Mapping[str, Any]) -> dict[str, Path]:
    """Write ``metrics_seeds.json``/``.csv``/``.md`` into ``out_dir`` (atomically, together)."""
    if agg.get("format") != SEED_METRICS_FORMAT:
        raise InvalidInputError(
            "agg", f"expected format {SEED_METRICS_FORMAT!r}, got {agg.get('format')!r}"
        )
    out = Path(out_dir)
    paths = {
        "json": out / "metrics_seeds.json",
        "csv": out / "metrics_seeds.csv",
        "md": out / "metrics_seeds.md",
    }
    texts = (_json_text(agg), seeds_to_csv(agg), seeds_to_markdown(agg))
    atomic_write_texts(dict(zip(paths.values(), texts, strict=True)))  # all three or none
    return paths


# --------------------------------------------------------------------------------------
# Sweeps


SWEEP_COLUMNS: tuple[str, ...] = (
    "param_value",
    "step",
    "method",
    "mean_mm",
    "std_mm",
    "n_points",
    "chamfer_mm",
    "fscore_1mm",
)
"""Columns of a sweep CSV after its first column ``param_name``."""


@dataclass(frozen=True)
class SweepTable:
    """Error against a swept parameter: one row per (value, step, method)."""

    param_name: str
    """The swept parameter with its unit, e.g. ``"pose_noise_mm"`` or ``"frames"``."""
    rows: list[dict[str, Any]] = field(default_factory=list)
    """Dicts with the keys of :data:`SWEEP_COLUMNS`; metric values may be None."""

    def __post_init__(self) -> None:
        if not self.param_name or "," in self.param_name:
            raise InvalidInputError(
                "param_name", f"must be a non-empty name without commas, got {self.param_name!r}"
            )
        if not self.rows:
            raise InvalidInputError(self.param_name, "a sweep needs at least one row")

    def values(self) -> list[float]:
        """The swept values, sorted."""
        return sorted({float(r["param_value"]) for r in self.rows})

    def methods(self) -> list[str]:
        return _method_order({r["method"] for r in self.rows})

    def last_step(self) -> int:
        return max(int(r["step"]) for r in self.rows)


def tabulate_sweep(param_name: str, runs: Sequence[tuple[float, Mapping[str, Any]]]) -> SweepTable:
    """Error against a swept parameter from one ``metrics.json`` per parameter value.

    runs : (value, metrics dict) pairs, e.g. ``[(10, m10), (30, m30), ...]`` for frames.
    """
    if not runs:
        raise InvalidInputError(param_name, "no sweep run given")
    seen: set[float] = set()
    rows = []
    for value, metrics in runs:
        v = float(value)
        if not math.isfinite(v):
            raise InvalidInputError(param_name, f"swept value must be finite, got {value}")
        if v in seen:
            raise InvalidInputError(param_name, f"value {v:g} appears twice")
        seen.add(v)
        validate_metrics(metrics, f"{param_name}={v:g}")
        for s in metrics["steps"]:
            for m in _method_order(list(s["methods"])):
                c = s["methods"][m]
                rows.append(
                    {
                        "param_value": v,
                        "step": int(s["step"]),
                        "method": m,
                        **{k: c[k] for k in SWEEP_COLUMNS[3:]},
                    }
                )
    rows.sort(key=lambda r: (r["param_value"], r["step"]))
    return SweepTable(param_name, rows)


def sweep_to_csv(table: SweepTable) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["param_name", *SWEEP_COLUMNS])
    for r in table.rows:
        w.writerow(
            [
                table.param_name,
                *(
                    "" if r[k] is None else repr(r[k]) if isinstance(r[k], float) else r[k]
                    for k in SWEEP_COLUMNS
                ),
            ]
        )
    return buf.getvalue()


def write_sweep_csv(path: str | Path, table: SweepTable) -> Path:
    """Write a sweep table as CSV (atomically); header ``param_name`` + :data:`SWEEP_COLUMNS`."""
    atomic_write_text(path, sweep_to_csv(table))
    return Path(path)


def read_sweep_csv(path: str | Path) -> SweepTable:
    """Read a CSV written by :func:`write_sweep_csv`; any malformed row (short, long, not
    a number) is one error naming the file and its line."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(path, "sweep CSV is missing")
    text = read_text_limited(path, "sweep CSV")  # size limit, UTF-8, one error naming it
    expected = ["param_name", *SWEEP_COLUMNS]
    reader = csv.reader(io.StringIO(text, newline=""))
    raw: list[tuple[int, dict[str, str]]] = []
    try:
        header = next(reader, None)
        if header != expected:
            raise InvalidInputError(path, f"expected columns {expected}, got {header}"[:300])
        for fields in reader:  # a blank line too is a row of the wrong length
            if len(fields) != len(expected):
                got = f"expected {len(expected)} fields, got {len(fields)}"
                raise InvalidInputError(path, f"line {reader.line_num}: {got}")
            raw.append((reader.line_num, dict(zip(expected, fields, strict=True))))
    except csv.Error as exc:  # an over-long field, a stray quote
        raise InvalidInputError(path, f"line {reader.line_num}: {exc}") from None
    if not raw:
        raise InvalidInputError(path, "sweep CSV has no rows")
    names = {r["param_name"] for _, r in raw}
    if len(names) != 1:
        raise InvalidInputError(path, f"expected one param_name, got {sorted(names)}"[:300])
    rows = []
    for line, r in raw:
        try:
            value = float(r["param_value"])
            row = {
                "param_value": value,
                "step": int(r["step"]),
                "method": r["method"],
                **{
                    k: (None if r[k] == "" else (int(r[k]) if k == "n_points" else float(r[k])))
                    for k in SWEEP_COLUMNS[3:]
                },
            }
        except ValueError as exc:
            raise InvalidInputError(path, f"line {line}: {exc}"[:300]) from None
        if not math.isfinite(value):
            raise InvalidInputError(
                path, f"line {line}: param_value must be a finite number, got {r['param_value']}"
            )
        rows.append(row)
    return SweepTable(names.pop(), rows)
