"""A self-contained HTML report of an experiment: tables, plots, depth panels, 3D view.

The page is one file that works offline (no network exists where it is opened): the
plotly.js bundle is embedded once in ``<head>``, images are base64 PNGs, and the 3D view
is a plotly ``Mesh3d`` of decimated meshes. Sections, each shown when its input is given:

- the paper's table (correspondence error mean ± std (n) per step x method) and the surface
  metrics table, from ``metrics.json`` (:mod:`chisel.eval.tables`);
- error against step, one line per method (error bars = std);
- sweeps: error at the last step against a swept parameter (sequence length, pose noise,
  depth noise, ...), from sweep CSVs (:func:`chisel.eval.tables.write_sweep_csv`);
- per-step panels like the paper's Figure 4: frame RGB, preoperative depth, GT depth,
  estimated depth, updated-model depth (one shared colour range per panel) and the change
  mask; stored in a *panels file* (npz, see :func:`write_panels`);
- the updated CT: axial and coronal slices through the change box per step, preoperative,
  true and each method's updated CT, removed region outlined, updated-CT Dice beside
  (:mod:`chisel.eval.ct_slices`: window, orientation and outlines);
- the preoperative and updated meshes in 3D, the updated mesh coloured by its distance to
  the preoperative surface (removed tissue stands out above ``removed_threshold_mm``).
"""

from __future__ import annotations

import html
import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import open3d as o3d
import plotly.graph_objects as go
import plotly.io as pio
import plotly.offline
import trimesh

from chisel.core.atomic import atomic_write_text
from chisel.core.errors import InvalidInputError
from chisel.eval.ct_slices import CT_SLICES_CSS, CtSlice, ct_slices_html
from chisel.eval.metrics import (
    RoiBox,
)
from chisel.eval.panels import (  # noqa: F401 - re-exported: the panels moved there
    PANEL_DEPTH_KEYS,
    PANEL_IMAGE_KEYS,
    PANELS_FORMAT,
    PANELS_VERSION,
    StepPanel,
    make_step_panel,
    png_data_uri,
    read_panels,
    write_panels,
)
from chisel.eval.surface import (
    point_to_mesh_distance,
)
from chisel.eval.tables import (
    METRIC_KEYS,
    SweepTable,
    table_methods,
    validate_metrics,
)

log = logging.getLogger(__name__)


_PANEL_TITLES = {
    "rgb": "frame RGB",
    "preop_depth_mm": "preoperative depth",
    "gt_depth_mm": "ground-truth depth",
    "estimated_depth_mm": "estimated depth",
    "updated_depth_mm": "updated-model depth",
    "change_mask": "change mask",
}

SIZE_WARNING_BYTES = 15 * 1024 * 1024
"""A report larger than this is logged as a warning (decimate harder)."""


# --------------------------------------------------------------------------------------
# Inputs


@dataclass(frozen=True)
class ReportMeshes:
    """The preoperative and updated meshes for the 3D view (world mm)."""

    preop: trimesh.Trimesh
    """Preoperative model surface."""
    updated: trimesh.Trimesh
    """Updated model surface after the last step."""
    removed_threshold_mm: float = 0.5
    """Updated-mesh vertices farther than this from the preoperative surface are highlighted."""
    max_faces: int = 60_000
    """Each mesh is decimated (quadric) to at most this many triangles to keep the page small."""
    roi_box: RoiBox | None = None
    """The ROI box, drawn as a wireframe when given."""

    def __post_init__(self) -> None:
        for name in ("preop", "updated"):
            m = getattr(self, name)
            if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
                raise InvalidInputError(f"{name} mesh", "expected a non-empty trimesh.Trimesh")
        if not self.removed_threshold_mm > 0:
            raise InvalidInputError(
                "removed_threshold_mm", f"must be positive, got {self.removed_threshold_mm}"
            )
        if int(self.max_faces) < 100:
            raise InvalidInputError("max_faces", f"must be >= 100, got {self.max_faces}")


# --------------------------------------------------------------------------------------
# Images


def depth_range_mm(depths: Sequence[np.ndarray]) -> tuple[float, float]:
    """Shared colour range of several depth maps: 1st-99th percentile of all valid pixels.

    depths : (H, W) float32 mm, NaN = invalid. Returns (vmin, vmax) mm with vmax > vmin.
    """
    vals = np.concatenate([d[np.isfinite(d)] for d in depths]) if depths else np.empty(0)
    if vals.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(vals, [1, 99])
    if hi - lo < 1e-6:
        hi = lo + 1.0
    return float(lo), float(hi)


def colorize_depth(depth_mm: np.ndarray, vmin_mm: float, vmax_mm: float) -> np.ndarray:
    """Colour-map a depth map (viridis, near = dark); no surface = black.

    depth_mm : (H, W) float32 mm, NaN = invalid. Returns (H, W, 3) uint8 RGB.
    """
    d = np.asarray(depth_mm, dtype=np.float32)
    valid = np.isfinite(d)
    t = np.clip((np.where(valid, d, vmin_mm) - vmin_mm) / (vmax_mm - vmin_mm), 0.0, 1.0)
    bgr = cv2.applyColorMap(np.round(t * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    rgb[~valid] = 0
    return rgb


def colorize_mask(mask: np.ndarray, rgb: np.ndarray | None) -> np.ndarray:
    """Change mask as an image: changed pixels red over the dimmed frame (or over black).

    mask : (H, W) bool.  rgb : (H, W, 3) uint8 or None. Returns (H, W, 3) uint8.
    """
    base = np.zeros((*mask.shape, 3), np.uint8) if rgb is None else (rgb // 2)
    out = base.copy()
    out[mask] = (np.array([255, 40, 40]) * 0.8 + base[mask] * 0.2).astype(np.uint8)
    return out


def _colorbar_png(vmin_mm: float, vmax_mm: float, width: int = 256) -> str:
    ramp = np.linspace(vmin_mm, vmax_mm, width, dtype=np.float32)[None].repeat(12, axis=0)
    return png_data_uri(colorize_depth(ramp, vmin_mm, vmax_mm))


# --------------------------------------------------------------------------------------
# Figures


_PLOT_CONFIG = {"displaylogo": False, "responsive": True}


def _fig_html(fig: go.Figure, div_id: str) -> str:
    return pio.to_html(
        fig, include_plotlyjs=False, full_html=False, div_id=div_id, config=_PLOT_CONFIG
    )


def error_vs_step_figure(metrics: Mapping[str, Any]) -> go.Figure:
    """Correspondence error (mean, error bar = std) per step, one line per method."""
    fig = go.Figure()
    for m in table_methods(metrics):
        xs, ys, es, ns = [], [], [], []
        for s in metrics["steps"]:
            c = s["methods"].get(m)
            if c is None:
                continue
            xs.append(s["label"])
            ys.append(c["mean_mm"])
            es.append(c["std_mm"])
            ns.append(c["n_points"])
        fig.add_trace(
            go.Scatter(
                x=xs,
                y=ys,
                error_y={"type": "data", "array": es, "visible": True},
                mode="lines+markers",
                name=m,
                customdata=ns,
                hovertemplate="%{x}: %{y:.3f} mm (n=%{customdata})<extra>" + m + "</extra>",
            )
        )
    fig.update_layout(
        title="Correspondence error per step (mean ± std)",
        xaxis_title="step",
        yaxis_title="error (mm)",
        height=420,
        template="plotly_white",
        xaxis={
            "type": "category",
            "categoryorder": "array",
            "categoryarray": [s["label"] for s in metrics["steps"]],
        },
    )
    return fig


def sweep_figure(name: str, table: SweepTable) -> go.Figure:
    """Error at the sweep's last step against the swept value, one line per method."""
    step = table.last_step()
    fig = go.Figure()
    for m in table.methods():
        rows = sorted(
            (
                r
                for r in table.rows
                if r["method"] == m and r["step"] == step and r["mean_mm"] is not None
            ),
            key=lambda r: r["param_value"],
        )
        if not rows:
            continue
        fig.add_trace(
            go.Scatter(
                x=[r["param_value"] for r in rows],
                y=[r["mean_mm"] for r in rows],
                error_y={
                    "type": "data",
                    "array": [r["std_mm"] or 0.0 for r in rows],
                    "visible": True,
                },
                mode="lines+markers",
                name=m,
            )
        )
    fig.update_layout(
        title=f"{name}: error at step {step} vs {table.param_name} (mean ± std)",
        xaxis_title=table.param_name,
        yaxis_title="error (mm)",
        height=380,
        template="plotly_white",
    )
    return fig


def _to_o3d(mesh: trimesh.Trimesh) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)),
    )


def decimate(mesh: trimesh.Trimesh, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric-decimate ``mesh`` to at most ``max_faces`` triangles (Open3D).

    Returns (vertices (V, 3) float32 mm, faces (F, 3) int32).
    """
    if len(mesh.faces) <= max_faces:
        return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    simple = _to_o3d(mesh).simplify_quadric_decimation(target_number_of_triangles=int(max_faces))
    simple.remove_unreferenced_vertices()
    return np.asarray(simple.vertices, np.float32), np.asarray(simple.triangles, np.int32)


def _box_wireframe(box: RoiBox) -> go.Scatter3d:
    lo, hi = box.min_mm, box.max_mm
    c = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
    edges = [(i, i ^ (1 << k)) for i in range(8) for k in range(3) if not (i >> k) & 1]
    xs, ys, zs = [], [], []
    for a, b in edges:
        xs += [c[a, 0], c[b, 0], None]
        ys += [c[a, 1], c[b, 1], None]
        zs += [c[a, 2], c[b, 2], None]
    return go.Scatter3d(
        x=xs, y=ys, z=zs, mode="lines", name="ROI box", line={"color": "black", "width": 3}
    )


def mesh_figure(meshes: ReportMeshes) -> go.Figure:
    """Interactive 3D view: preop mesh (translucent) and the updated mesh coloured by distance.

    The updated mesh's vertices are coloured by their exact distance to the full-resolution
    preoperative surface: grey up to ``removed_threshold_mm``, then orange to red.
    """
    pv, pf = decimate(meshes.preop, meshes.max_faces)
    uv, uf = decimate(meshes.updated, meshes.max_faces)
    dist = point_to_mesh_distance(uv, meshes.preop).astype(np.float32)
    thr = float(meshes.removed_threshold_mm)
    cmax = max(2.0 * thr, float(np.percentile(dist, 99.5)))
    k = thr / cmax
    colorscale = [
        [0.0, "rgb(200,200,200)"],
        [k, "rgb(200,200,200)"],
        [min(k + 1e-6, 1.0), "rgb(255,170,0)"],
        [1.0, "rgb(200,0,0)"],
    ]
    removed = int(np.count_nonzero(dist > thr))
    fig = go.Figure()
    fig.add_trace(
        go.Mesh3d(
            x=pv[:, 0],
            y=pv[:, 1],
            z=pv[:, 2],
            i=pf[:, 0],
            j=pf[:, 1],
            k=pf[:, 2],
            color="rgb(90,140,230)",
            opacity=0.25,
            name="preoperative model",
            showlegend=True,
            hoverinfo="skip",
        )
    )
    fig.add_trace(
        go.Mesh3d(
            x=uv[:, 0],
            y=uv[:, 1],
            z=uv[:, 2],
            i=uf[:, 0],
            j=uf[:, 1],
            k=uf[:, 2],
            intensity=dist,
            cmin=0.0,
            cmax=cmax,
            colorscale=colorscale,
            colorbar={"title": {"text": "distance to<br>preop (mm)"}},
            name=f"updated model ({removed} vertices > {thr:g} mm)",
            showlegend=True,
            hovertemplate="%{intensity:.2f} mm<extra>updated</extra>",
            flatshading=False,
        )
    )
    if meshes.roi_box is not None:
        fig.add_trace(_box_wireframe(meshes.roi_box))
    fig.update_layout(
        title="Preoperative (blue, translucent) and updated model; removed region highlighted",
        height=650,
        scene={
            "aspectmode": "data",
            "xaxis_title": "x (mm)",
            "yaxis_title": "y (mm)",
            "zaxis_title": "z (mm)",
        },
        legend={"x": 0.0, "y": 1.0},
        margin={"l": 0, "r": 0, "t": 40, "b": 0},
    )
    return fig


# --------------------------------------------------------------------------------------
# HTML


_CSS = """
body { font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1300px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f2f4f8; } td.l, th.l { text-align: left; }
.panel { display: flex; flex-wrap: wrap; gap: 0.6em; margin-bottom: 1.2em; }
figure { margin: 0; } figcaption { font-size: 0.85em; text-align: center; }
img.im { image-rendering: pixelated; width: 220px; border: 1px solid #ddd; }
.cbar { display: flex; align-items: center; gap: 0.4em; font-size: 0.85em; }
.note { color: #555; font-size: 0.9em; }
.scroll { overflow-x: auto; }
"""


def _num(x: Any, digits: int = 3) -> str:
    if x is None:
        return "-"
    if isinstance(x, int):
        return str(x)
    return f"{x:.{digits}f}"


def main_table_html(metrics: Mapping[str, Any]) -> str:
    """The paper's table: rows = steps, columns = methods, cells = mean ± std (n)."""
    methods = table_methods(metrics)
    head = "".join(f"<th>{html.escape(m)}</th>" for m in methods)
    rows = []
    for s in metrics["steps"]:
        cells = []
        for m in methods:
            c = s["methods"].get(m)
            cells.append(
                "<td>-</td>"
                if c is None
                else f"<td>{c['mean_mm']:.3f} ± {c['std_mm']:.3f} <small>(n={c['n_points']})</small></td>"
            )
        rows.append(f"<tr><td class='l'>{html.escape(s['label'])}</td>{''.join(cells)}</tr>")
    return f"<table id='main-table'><tr><th class='l'>step</th>{head}</tr>{''.join(rows)}</table>"


def surface_table_html(metrics: Mapping[str, Any]) -> str:
    """Every metric of every (step, method) cell."""
    keys = [k for k in METRIC_KEYS if k not in ("mean_mm", "std_mm")]
    head = "".join(f"<th>{html.escape(k)}</th>" for k in keys)
    rows = []
    for s in metrics["steps"]:
        for m in table_methods(metrics):
            c = s["methods"].get(m)
            if c is None:
                continue
            cells = "".join(f"<td>{_num(c.get(k))}</td>" for k in keys)
            rows.append(
                f"<tr><td class='l'>{html.escape(s['label'])}</td>"
                f"<td class='l'>{html.escape(m)}</td>{cells}</tr>"
            )
    return (
        f"<table id='surface-table'><tr><th class='l'>step</th><th class='l'>method</th>{head}</tr>"
        f"{''.join(rows)}</table>"
    )


def panel_html(panel: StepPanel) -> str:
    """A row of images for one panel, depth maps on one shared colour range."""
    images = panel.images()
    depths = [images[k] for k in PANEL_DEPTH_KEYS if k in images]
    vmin, vmax = depth_range_mm(depths)
    figs = []
    for key, arr in images.items():
        if key == "rgb":
            rgb = arr
        elif key == "change_mask":
            rgb = colorize_mask(arr, panel.rgb)
        else:
            rgb = colorize_depth(arr, vmin, vmax)
        figs.append(
            f"<figure><img class='im' alt='{key}' src='{png_data_uri(rgb)}'>"
            f"<figcaption>{_PANEL_TITLES[key]}</figcaption></figure>"
        )
    bar = ""
    if depths:
        bar = (
            f"<div class='cbar'>{vmin:.1f} mm <img alt='depth colour bar' "
            f"src='{_colorbar_png(vmin, vmax)}' width='256' height='12'> {vmax:.1f} mm "
            "(black = no surface)</div>"
        )
    title = "preop" if panel.step == 0 else f"bite {panel.step}"
    return (
        f"<h3>{title}, frame {panel.frame_index}</h3><div class='panel'>{''.join(figs)}</div>{bar}"
    )


def build_report_html(
    metrics: Mapping[str, Any],
    panels: Sequence[StepPanel] = (),
    meshes: ReportMeshes | None = None,
    sweeps: Mapping[str, SweepTable] | None = None,
    title: str = "Endoscopic Chisel: evaluation report",
    ct_slices: Sequence[CtSlice] = (),
) -> str:
    """The report as one HTML string (plotly.js embedded; no external resource)."""
    validate_metrics(metrics, "metrics")
    parts = [
        f"<h1>{html.escape(title)}</h1>",
        f"<p class='note'>Experiment <b>{html.escape(str(metrics['experiment']))}</b>. "
        "Errors in mm: distances between same-pixel points of ground-truth and model depth "
        "renders inside the ROI box (see docs/evaluation.md).</p>",
        "<h2>Correspondence error per step</h2>",
        main_table_html(metrics),
        _fig_html(error_vs_step_figure(metrics), "fig-error-vs-step"),
        "<h2>Surface metrics inside the ROI box</h2>",
        f"<div class='scroll'>{surface_table_html(metrics)}</div>",
    ]
    protocol = metrics.get("protocol") or {}
    if protocol:
        parts.append(
            "<details><summary>protocol</summary><pre>"
            + html.escape(json.dumps(protocol, indent=2))
            + "</pre></details>"
        )
    if sweeps:
        parts.append("<h2>Sweeps</h2>")
        for i, (name, table) in enumerate(sweeps.items()):
            parts.append(_fig_html(sweep_figure(name, table), f"fig-sweep-{i}"))
    if panels:
        parts.append("<h2>Per-step panels</h2>")
        parts += [panel_html(p) for p in sorted(panels, key=lambda p: (p.step, p.frame_index))]
    if ct_slices:
        parts.append("<h2>Updated CT through the change box</h2>")
        parts.append(ct_slices_html(ct_slices))
    if meshes is not None:
        parts.append("<h2>3D model</h2>")
        parts.append(_fig_html(mesh_figure(meshes), "fig-meshes"))
    body = "\n".join(parts)
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)}</title><style>{_CSS}{CT_SLICES_CSS}</style>\n"
        f"<script type='text/javascript'>{plotly.offline.get_plotlyjs()}</script>\n"
        f"</head><body>\n{body}\n</body></html>\n"
    )


def write_report(
    out_html: str | Path,
    metrics: Mapping[str, Any],
    panels: Sequence[StepPanel] | None = None,
    meshes: ReportMeshes | None = None,
    sweeps: Mapping[str, SweepTable] | None = None,
    title: str = "Endoscopic Chisel: evaluation report",
    ct_slices: Sequence[CtSlice] | None = None,
) -> Path:
    """Write the self-contained HTML report (atomically); returns its path."""
    text = build_report_html(metrics, panels or (), meshes, sweeps, title, ct_slices or ())
    size = len(text.encode("utf-8"))
    if size > SIZE_WARNING_BYTES:
        log.warning("report is %.1f MB; lower ReportMeshes.max_faces", size / 2**20)
    atomic_write_text(out_html, text)
    return Path(out_html)
