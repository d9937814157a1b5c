"""Snakemake wrapper: score one surgical step (chisel.eval.step.evaluate_step)."""

import logging

from chisel.eval.step import (
    evaluate_step,
)
from chisel.eval.tables import (
    write_step_metrics,
)
from chisel.io.manifest import named_path, read_json_manifest

sm = snakemake  # noqa: F821 - injected by Snakemake
logging.basicConfig(
    filename=sm.log[0], level=logging.INFO, format="%(levelname)s %(name)s: %(message)s"
)

manifest = read_json_manifest(sm.input.manifest)
step = int(sm.wildcards.step)
steps = {s["step"]: s for s in manifest["steps"]}
masks = dict(zip(sm.params.mask_methods, sm.input.masks, strict=True)) or None
result = evaluate_step(
    gt_mesh_path=named_path(sm.input.manifest, steps[step]["mesh"], f"steps[{step}].mesh"),
    method_mesh_paths=dict(zip(sm.params.methods, sm.input.meshes, strict=True)),
    eval_sequence_path=sm.params.eval_sequence,
    roi_box_mm=[v for corner in manifest["roi_box_mm"] for v in corner],
    step=step,
    change_mask_paths=masks,
    change_sequence_path=sm.params.change_sequence if masks else None,
    start_surface_paths=dict(zip(sm.params.mask_methods, sm.input.start_models, strict=True))
    or None,
    removal_model_paths=dict(zip(sm.params.methods, sm.input.models, strict=True)),
    preop_model_path=dict(zip(sm.params.methods, sm.input.preop_models, strict=True)),
    ct_label_paths=(
        named_path(sm.input.manifest, steps[0]["ct_label"], "steps[].ct_label"),
        named_path(sm.input.manifest, steps[step]["ct_label"], "steps[].ct_label"),
    ),
)
write_step_metrics(sm.output.metrics, result)
