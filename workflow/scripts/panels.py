"""Snakemake wrapper: Figure-4 panels (chisel.eval.report.make_step_panel) for every step."""

import logging

import numpy as np
import trimesh

from chisel.eval.report import make_step_panel, write_panels
from chisel.io.sequence import Sequence

sm = snakemake  # noqa: F821 - injected by Snakemake
logging.basicConfig(filename=sm.log[0], level=logging.INFO)

render_dir = sm.input.index.rsplit("/", 1)[0]
preop = trimesh.load(sm.input.preop, force="mesh")
panels = []
for k, step in enumerate(sm.params.steps):
    seq = Sequence(f"{render_dir}/step_{step:02d}")
    i = len(seq) // 2  # the middle frame of the step's sequence
    with np.load(sm.input.masks[k], allow_pickle=False) as z:
        where = np.flatnonzero(z["frame_index"] == i)
        mask = z["masks"][where[0]] if where.size else None
    estimate = Sequence(sm.input.pred[k]).depth_mm(i)
    updated = trimesh.load(sm.input.updated[k], force="mesh")
    panels.append(make_step_panel(step, seq.frame(i), seq.camera, preop, updated, estimate, mask))
write_panels(sm.output.panels, panels)
