"""CLI: ``chisel export-ct`` (the updated CT a navigation system or 3D Slicer can load).

Thin wrapper: reads the CT (:func:`chisel.io.ct.read_ct_volume`) and the model, calls
:func:`chisel.ct_export.updated_ct`, writes the result with the CT's own header and
orientation (:func:`chisel.io.ct.write_ct_volume`, atomic; nothing written on error).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from chisel.cli.args import Output
from chisel.core.errors import InvalidInputError

log = logging.getLogger(__name__)

_DESCRIPTION = """\
Write the preoperative CT with the tissue the model removed set to air, on the CT's own
grid, with its header and orientation.

  removed   CT voxels that are tissue in the CT (label > 0, or above -480 HU) and observed
            free space in the model (signed distance > 0 at the voxel centre, weight > 0)
            and, with --preop-model, not already free space in the preoperative model
  label CT  removed voxels take the air label 0
  HU CT     air (-1000 HU) with a partial-volume ramp one CT voxel wide across the new
            boundary, from the model's signed distance d: f = clip(0.5 - d / voxel, 0, 1),
            HU = -1000 + (HU_ct + 1000) f (never raised)

Formats: CT = NIfTI (.nii/.nii.gz, RAS affine in the file) or NRRD (.nrrd), any orientation;
the output has the input's format (by --out's suffix). Model = .npz (docs/updater.md), world
mm in the CT's LPS frame. Refused, naming the file: a model whose grid does not overlap the
CT, a CT that does not cover the model, 4-D or sheared volumes, NaN affines.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export-ct",
        help="the preoperative CT with the tissue the model removed set to air",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--model", required=True, type=Path, help="updated model file (.npz)")
    p.add_argument(
        "--ct", required=True, type=Path, help="preoperative CT volume (.nii/.nii.gz/.nrrd)"
    )
    p.add_argument(
        "--out",
        required=True,
        type=Path,
        action=Output,
        help="updated CT (.nii/.nii.gz/.nrrd), written atomically",
    )
    p.add_argument(
        "--preop-model",
        type=Path,
        help="the preoperative model the update started from (.npz): tissue it already held "
        "as free space (CT detail thinner than its voxels) is kept, so that only what the "
        "update carved is removed (recommended)",
    )
    p.add_argument(
        "--kind",
        choices=("auto", "intensity", "label"),
        default="auto",
        help="CT contents: intensity HU, labels (0 = air), or auto (default: intensity when "
        "any value is below -100)",
    )
    p.set_defaults(func=_cmd_export_ct)


def _cmd_export_ct(args: argparse.Namespace) -> int:
    from chisel.ct_export import updated_ct
    from chisel.io.ct import VOLUME_SUFFIXES, read_ct_volume, write_ct_volume
    from chisel.model import TsdfModel

    out_name = args.out.name.lower()
    if not out_name.endswith((".nii", ".nii.gz", ".nrrd")):
        raise InvalidInputError(args.out, "output must be .nii, .nii.gz or .nrrd")
    if not args.ct.name.lower().endswith(VOLUME_SUFFIXES):
        raise InvalidInputError(args.ct, f"CT must be a volume, one of {VOLUME_SUFFIXES}")
    ct = read_ct_volume(args.ct, args.kind)
    model = TsdfModel.load(args.model)
    preop = TsdfModel.load(args.preop_model) if args.preop_model else None
    result = updated_ct(ct, model, model_source=str(args.model), preop=preop)
    write_ct_volume(args.out, result.volume, like=ct)
    spacing = ct.spacing_mm
    log.info(
        "export-ct: %d voxels removed (%.1f mm3) -> %s",
        int(result.removed.sum()),
        float(result.removed.sum() * spacing.prod()),
        args.out,
    )
    return 0
