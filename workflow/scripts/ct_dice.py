"""Snakemake wrapper: updated-CT Dice of the removed region per method for one step
(chisel.ct_export.removed_region_scores), against the step's true label CT."""

import json
import logging

from chisel.core.atomic import atomic_write_text
from chisel.ct_export import removed_region_scores
from chisel.io.ct import read_ct_volume
from chisel.io.manifest import named_path, read_json_manifest

sm = snakemake  # noqa: F821 - injected by Snakemake
logging.basicConfig(filename=sm.log[0], level=logging.INFO, format="%(levelname)s: %(message)s")

manifest = read_json_manifest(sm.input.manifest)
step = int(sm.wildcards.step)
steps = {s["step"]: s for s in manifest["steps"]}
before = read_ct_volume(named_path(sm.input.manifest, steps[0]["ct_hu"], "steps[0].ct_hu"))
truth = read_ct_volume(
    named_path(sm.input.manifest, steps[step]["ct_label"], f"steps[{step}].ct_label")
)
scores = {}
for method, path in zip(sm.params.methods, sm.input.cts, strict=True):
    scores[method] = removed_region_scores(before, read_ct_volume(path), truth)
    logging.info(
        "step %d %s: updated-CT Dice of the removed region %.3f",
        step,
        method,
        scores[method]["dice"],
    )
    print(f"step {step} {method}: updated-CT removed-region Dice {scores[method]['dice']:.3f}")
out = {
    "step": step,
    "updated_ct": scores,
    "ct": dict(zip(sm.params.methods, sm.input.cts, strict=True)),
}
atomic_write_text(sm.output[0], json.dumps(out, indent=2) + "\n")
