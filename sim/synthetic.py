"""A tiny hand-made phantom folder for tests and benchmarks (not the anatomy generator).

A tissue block with a tunnel-shaped airway ending in a chamber; the chamber's far wall
is the target, and each surgical step cuts one more small box ("bite") out of it. It
follows the ``phantom.json`` contract of ``python -m phantoms generate`` so the whole
simulator can be tested without the ``phantoms`` package.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh

from chisel.core.atomic import atomic_dir

CHAMBER_CENTER_MM = np.array([38.0, 0.0, 0.0])
CHAMBER_RADIUS_MM = 9.0


BITE_EXTENTS_MM = np.array([4.0, 3.0, 4.0])


def bite_centers_mm(n_bites: int) -> np.ndarray:
    """(n_bites, 3) centres of the toy's box bites, mm."""
    return np.array(
        [
            [CHAMBER_CENTER_MM[0] + CHAMBER_RADIUS_MM + 0.5, -3.0 + 3.0 * k, 0.0]
            for k in range(n_bites)
        ]
    )


def toy_cut_faces(mesh: trimesh.Trimesh, n_bites: int) -> np.ndarray:
    """(F,) bool: faces of ``mesh`` lying on the surface of one of the first ``n_bites``
    bite boxes (the faces a cut created), from the boxes' planes (tolerance 1e-5 mm)."""
    c = np.asarray(mesh.triangles_center)
    half = BITE_EXTENTS_MM / 2.0
    out = np.zeros(len(c), dtype=bool)
    for center in bite_centers_mm(n_bites):
        q = np.abs(c - center) / half
        out |= (
            (q.max(axis=1) > 1.0 - 1e-5)
            & (q.max(axis=1) < 1.0 + 1e-5)
            & np.all(q <= 1.0 + 1e-5, axis=1)
        )
    return out


def toy_meshes(n_bites: int = 2) -> list[trimesh.Trimesh]:
    """Tissue meshes (closed, mm) of the preoperative state and after each bite."""
    block = trimesh.creation.box(extents=[60.0, 36.0, 36.0])
    block.apply_translation([30.0, 0.0, 0.0])
    tunnel = trimesh.creation.cylinder(radius=5.0, height=44.0, sections=48)
    tunnel.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    tunnel.apply_translation([16.0, 0.0, 0.0])
    chamber = trimesh.creation.icosphere(subdivisions=4, radius=CHAMBER_RADIUS_MM)
    chamber.apply_translation(CHAMBER_CENTER_MM)
    mesh = block.difference(trimesh.boolean.union([tunnel, chamber]))
    meshes = [mesh]
    for center in bite_centers_mm(n_bites):
        bite = trimesh.creation.box(extents=BITE_EXTENTS_MM)
        bite.apply_translation(center)
        mesh = mesh.difference(bite)
        meshes.append(mesh)
    return meshes


def write_toy_phantom(out_dir: str | Path, n_bites: int = 2, seed: int = 0) -> Path:
    """Write the toy phantom folder (``phantom.json``, ``meshes/step_NN.ply`` and the cut-face
    labels ``meshes/step_NN_cut_faces.npy``, uint8 per face, as ``phantoms`` writes them)
    atomically."""
    meshes = toy_meshes(n_bites)
    out = Path(out_dir)
    target = CHAMBER_CENTER_MM + np.array([CHAMBER_RADIUS_MM, 0.0, 0.0])
    with atomic_dir(out, "phantom.json") as tmp:
        (tmp / "meshes").mkdir()
        steps = []
        for k, m in enumerate(meshes):
            rel = f"meshes/step_{k:02d}.ply"
            m.export(tmp / rel)
            cut = toy_cut_faces(m, k).astype(np.uint8)
            np.save(tmp / f"meshes/step_{k:02d}_cut_faces.npy", cut)
            before = meshes[k - 1].volume if k else m.volume
            steps.append(
                {
                    "step": k,
                    "name": "preop" if k == 0 else f"bite_{k}",
                    "mesh": rel,
                    "cut_faces": f"meshes/step_{k:02d}_cut_faces.npy",
                    "cut_face_count": int(cut.sum()),
                    "removed_volume_mm3": float(before - m.volume),
                }
            )
        manifest = {
            "format": "endoscopic-chisel/phantom",
            "version": 1,
            "seed": int(seed),
            "params": {"kind": "sim.synthetic toy phantom"},
            "steps": steps,
            "roi_box_mm": [[target[0] - 3.0, -6.0, -4.0], [target[0] + 4.0, 6.0, 4.0]],
            "target": {
                "name": "chamber_wall",
                "center_mm": target.tolist(),
                "normal": [-1.0, 0.0, 0.0],
            },
            "airway_path_mm": [[x, 0.0, 0.0] for x in np.linspace(1.0, 36.0, 8)],
        }
        (tmp / "phantom.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m sim.synthetic --seed S --bites N --out DIR``: the phantom generator's
    command-line contract, for ``sim dataset --phantom-cmd`` in quick tests."""
    import argparse  # noqa: PLC0415 - only for the command line

    p = argparse.ArgumentParser(prog="python -m sim.synthetic", description=main.__doc__)
    p.add_argument("--seed", type=int, default=0, help="recorded in phantom.json (0)")
    p.add_argument("--bites", type=int, default=2, help="surgical steps (2)")
    p.add_argument("--out", type=Path, required=True, help="phantom folder (replaced atomically)")
    args = p.parse_args(argv)
    if args.bites < 0:
        p.error("--bites must be >= 0")
    write_toy_phantom(args.out, args.bites, args.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
