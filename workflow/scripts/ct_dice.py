"""Snakemake wrapper: updated-CT Dice of the removed region per method for one step
(chisel.ct_export.removed_region_scores), against the step's true label CT, and the
axial and coronal slices through the change box that the report shows
(chisel.eval.ct_slices)."""

import json
import logging

from chisel.core.atomic import atomic_write_text
from chisel.ct_export import removed_region_scores
from chisel.eval.ct_slices import make_ct_slices, write_ct_slices
from chisel.eval.metrics import RoiBox
from chisel.io.ct import read_ct_volume
from chisel.io.manifest import named_path, read_json_manifest

sm = snakemake  # noqa: F821 - injected by Snakemake
logging.basicConfig(filename=sm.log[0], level=logging.INFO, format="%(levelname)s: %(message)s")

manifest = read_json_manifest(sm.input.manifest)
step = int(sm.wildcards.step)
steps = {s["step"]: s for s in manifest["steps"]}


def step_ct(k, key):
    return read_ct_volume(named_path(sm.input.manifest, steps[k][key], f"steps[{k}].{key}"))


before = step_ct(0, "ct_hu")
truth = step_ct(step, "ct_label")
updated = {m: read_ct_volume(p) for m, p in zip(sm.params.methods, sm.input.cts, strict=True)}
scores = {}
for method, ct in updated.items():
    scores[method] = removed_region_scores(before, ct, truth)
    msg = (
        f"step {step} {method}: updated-CT removed-region Dice {scores[method]['dice']:.3f} "
        f"({scores[method]['predicted_voxels']} voxels removed, "
        f"{scores[method]['true_voxels']} truly removed)"
    )
    logging.info(msg)
    print(msg)
out = {
    "step": step,
    "updated_ct": scores,
    "ct": dict(zip(sm.params.methods, sm.input.cts, strict=True)),
}
atomic_write_text(sm.output.dice, json.dumps(out, indent=2) + "\n")
slices = make_ct_slices(
    step,
    before,
    updated,
    RoiBox.from_values([v for c in manifest["roi_box_mm"] for v in c], "phantom.json roi_box_mm"),
    truth_label=truth,
    truth_image=step_ct(step, "ct_hu"),
    dice={m: s["dice"] for m, s in scores.items()},
)
write_ct_slices(sm.output.slices, slices)
