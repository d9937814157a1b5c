"""A thin film of blood trickling downhill from a step's fresh cut (``blood.*``).

Pure functions of the step's mesh, its cut-face labels, gravity and a seed:

* :func:`fresh_cut_faces` tells the faces the current step cut from those earlier steps
  cut (the phantom's labels accumulate over steps);
* :func:`blood_film_weight` returns a per-face film coverage in [0, 1]: a few streaks
  start at random points of the cut's lower edge (where the tissue beside the cut lies
  downhill of it) and run along the steepest descent of gravity over the surface, face
  by face, until they have run their length, reach a face too flat to run on (the blood
  pools there) or a crease that runs back uphill (the blood collects in it). A face within
  half a streak's width of the streak, reached over the surface, is covered with
  ``strength * (1 - s / length)``, ``s`` the distance the blood ran: a film that thins out
  as it runs. Fresh cut faces themselves get 0 (they have the cut material's blood).

The renderer blends the faces' BSDF towards a smooth, dark-red principled BSDF with this
weight (``sim.materials.tissue_properties``, ``sim.spot_direct``).
"""

from __future__ import annotations

import numpy as np
import trimesh

from sim.config import BloodConfig

FLAT_SLOPE = 0.05
"""A face whose in-plane gravity is below this fraction of g (slope < ~3 deg) is flat:
blood stops running there."""
LOWER_EDGE_COS = 0.3
"""A cut's edge is a lower edge where the beside-face's downhill direction leaves the edge
within ~73 deg of its perpendicular (not along the side of the cut)."""


def fresh_cut_faces(
    mesh: trimesh.Trimesh,
    cut: np.ndarray,
    prev_mesh: trimesh.Trimesh | None,
    prev_cut: np.ndarray | None,
    tol_mm: float = 0.01,
) -> np.ndarray:
    """(F,) bool: cut faces of ``mesh`` that the step made, not an earlier one.

    The phantom labels every face any cutter made so far (``docs/phantoms.md``), and
    meshes of two steps share no face indices; a face is from an earlier cut when its
    centroid lies on the previous step's cut surface (within ``tol_mm``; the booleans move
    split vertices by a few um). ``prev_mesh`` None (step 0 or 1): every cut face is fresh.
    """
    cut = np.asarray(cut, dtype=bool)
    if prev_mesh is None or prev_cut is None or not np.any(prev_cut) or not cut.any():
        return cut.copy()
    old = trimesh.Trimesh(
        vertices=np.asarray(prev_mesh.vertices),
        faces=np.asarray(prev_mesh.faces)[np.asarray(prev_cut, dtype=bool)],
        process=False,
    )
    idx = np.flatnonzero(cut)
    _, dist, _ = trimesh.proximity.closest_point(old, np.asarray(mesh.triangles_center)[idx])
    fresh = cut.copy()
    fresh[idx[dist <= tol_mm]] = False
    return fresh


def _neighbours(faces: np.ndarray) -> np.ndarray:
    """(F, 3) int: the face across local edge k (vertices k, k+1) of each face; -1 on a
    boundary edge."""
    F = len(faces)
    e = np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    _, inv = np.unique(e, axis=0, return_inverse=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    out = np.full(3 * F, -1, dtype=np.int64)
    same = inv[order[1:]] == inv[order[:-1]]
    a, b = order[:-1][same], order[1:][same]
    out[a], out[b] = b // 3, a // 3
    return out.reshape(F, 3)


def _downhill(normals: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit in-plane gravity per face ((N, 3)) and its length (the slope, (N,))."""
    d = g - (normals @ g)[:, None] * normals
    slope = np.linalg.norm(d, axis=1)
    return d / np.maximum(slope, 1e-12)[:, None], slope


def _into_face(v: np.ndarray, f: np.ndarray, k: int, n: np.ndarray) -> np.ndarray:
    """Unit vector in the plane of face ``f`` (vertex ids), perpendicular to its local edge
    ``k`` and pointing into the face."""
    p0, p1, p2 = v[f[k]], v[f[(k + 1) % 3]], v[f[(k + 2) % 3]]
    m = np.cross(n, p1 - p0)
    m /= max(float(np.linalg.norm(m)), 1e-12)
    return m if float(np.dot(m, p2 - p0)) > 0 else -m


def _trace(
    v: np.ndarray,
    faces: np.ndarray,
    nbr: np.ndarray,
    normals: np.ndarray,
    g: np.ndarray,
    face: int,
    entry: int,
    p: np.ndarray,
    length_mm: float,
) -> tuple[np.ndarray, list[int]]:
    """The polyline ((M, 3), mm) a streak runs from ``p`` on local edge ``entry`` of
    ``face`` along the steepest descent, and the faces it crosses."""
    pts, crossed = [p], [face]
    left = length_mm
    for _ in range(100_000):
        n = normals[face]
        d, slope = _downhill(n[None], g)
        if slope[0] < FLAT_SLOPE:
            break  # flat: the blood pools here
        d = d[0]
        best_s, best_k = np.inf, -1
        f = faces[face]
        for k in range(3):
            if k == entry:
                continue
            a, e = v[f[k]], v[f[(k + 1) % 3]] - v[f[k]]
            den = float(np.dot(np.cross(d, e), n))
            if abs(den) < 1e-15:
                continue
            s = float(np.dot(np.cross(a - p, e), n)) / den
            t = float(np.dot(np.cross(a - p, d), n)) / den
            if s > 1e-9 and -1e-9 <= t <= 1 + 1e-9 and s < best_s:
                best_s, best_k = s, k
        if best_k < 0:
            break
        step = min(best_s, left)
        p = p + step * d
        pts.append(p)
        left -= step
        nxt = int(nbr[face, best_k])
        if left <= 0 or nxt < 0:
            break
        # The next face's downhill direction must leave the shared edge into that face,
        # else the edge is a crease the blood collects in.
        k_in = int(np.flatnonzero(nbr[nxt] == face)[0])
        d_next, slope_next = _downhill(normals[nxt][None], g)
        into = _into_face(v, faces[nxt], k_in, normals[nxt])
        if slope_next[0] < FLAT_SLOPE or float(np.dot(d_next[0], into)) <= 0:
            break
        face, entry = nxt, k_in
        crossed.append(face)
    return np.asarray(pts), crossed


def _paint(
    centers: np.ndarray,
    nbr: np.ndarray,
    pts: np.ndarray,
    crossed: list[int],
    half_width_mm: float,
    length_mm: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Faces within ``half_width_mm`` of the polyline ``pts``, reached over the surface
    from the crossed faces, and the distance ``s`` (mm) the blood ran to each.

    Faces behind the start (closest to the first point, on the uphill side) are left
    out: the film never rises above the cut."""
    seg_a, seg_b = pts[:-1], pts[1:]
    ab = seg_b - seg_a
    seg_len = np.linalg.norm(ab, axis=1)
    s0 = np.concatenate([[0.0], np.cumsum(seg_len)[:-1]])

    def run(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = centers[idx][:, None, :] - seg_a[None]
        raw = np.einsum("nmk,mk->nm", c, ab) / np.maximum(seg_len**2, 1e-18)
        u = np.clip(raw, 0.0, 1.0)
        dist = np.linalg.norm(c - u[..., None] * ab[None], axis=2)
        dist[:, 0] = np.where(raw[:, 0] < 0, np.inf, dist[:, 0])
        j = np.argmin(dist, axis=1)
        rows = np.arange(len(idx))
        return dist[rows, j], s0[j] + u[rows, j] * seg_len[j]

    if len(ab) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    seen = np.zeros(len(centers), dtype=bool)
    frontier = np.unique(np.asarray(crossed, dtype=np.int64))
    seen[frontier] = True
    found, runs = [frontier], [run(frontier)[1]]
    while len(frontier):
        cand = np.unique(nbr[frontier].ravel())
        cand = cand[(cand >= 0) & ~seen[cand]]
        seen[cand] = True
        dist, s = run(cand)
        keep = dist <= half_width_mm
        frontier = cand[keep]
        found.append(frontier)
        runs.append(s[keep])
    faces_out, s_out = np.concatenate(found), np.concatenate(runs)
    ok = s_out < length_mm
    return faces_out[ok], s_out[ok]


def blood_film_weight(
    mesh: trimesh.Trimesh, fresh: np.ndarray, cfg: BloodConfig, seed: int
) -> np.ndarray:
    """(F,) float32 film coverage in [0, 1] per face of ``mesh`` (see the module doc).

    mesh : the step's tissue (closed, mm, LPS world). fresh : (F,) bool, the faces this
    step cut (:func:`fresh_cut_faces`). cfg : the ``blood`` section (gravity, streak count,
    length and width ranges, strength). Same inputs and seed -> same weights; all zero
    without fresh cut faces or at zero strength.
    """
    faces = np.asarray(mesh.faces, dtype=np.int64)
    out = np.zeros(len(faces), dtype=np.float32)
    fresh = np.asarray(fresh, dtype=bool)
    if cfg.strength <= 0 or not fresh.any():
        return out
    v = np.asarray(mesh.vertices, dtype=np.float64)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)
    g = np.asarray(cfg.gravity, dtype=np.float64)
    g /= np.linalg.norm(g)
    nbr = _neighbours(faces)
    # Lower edges: a fresh face's edge whose other face is not fresh and lies downhill.
    fi, ki = np.nonzero(fresh[:, None] & (nbr >= 0) & ~fresh[np.maximum(nbr, 0)])
    starts: list[tuple[int, int, float]] = []
    for f_cut, k in zip(fi.tolist(), ki.tolist(), strict=True):
        m = int(nbr[f_cut, k])
        k_in = int(np.flatnonzero(nbr[m] == f_cut)[0])
        d, slope = _downhill(normals[m][None], g)
        into = _into_face(v, faces[m], k_in, normals[m])
        if slope[0] >= FLAT_SLOPE and float(np.dot(d[0], into)) > LOWER_EDGE_COS:
            e = v[faces[m][(k_in + 1) % 3]] - v[faces[m][k_in]]
            starts.append((m, k_in, float(np.linalg.norm(e))))
    if not starts:
        return out
    rng = np.random.default_rng([int(seed), 23])
    n_streaks = int(rng.integers(cfg.streaks[0], cfg.streaks[1] + 1))
    # Start points uniform along the lower edge: edges drawn by length.
    lengths = np.array([s[2] for s in starts])
    picks = rng.choice(len(starts), size=n_streaks, p=lengths / lengths.sum())
    centers = np.asarray(mesh.triangles_center, dtype=np.float64)
    for i in picks.tolist():
        face, k_in, _ = starts[i]
        t = float(rng.uniform(0.1, 0.9))
        length = float(rng.uniform(*cfg.film_length_mm))
        half_width = 0.5 * float(rng.uniform(*cfg.width_mm))
        f = faces[face]
        p0 = v[f[k_in]] + t * (v[f[(k_in + 1) % 3]] - v[f[k_in]])
        pts, crossed = _trace(v, faces, nbr, normals, g, face, k_in, p0, length)
        hit, s = _paint(centers, nbr, pts, crossed, half_width, length)
        w = (cfg.strength * (1.0 - s / length)).astype(np.float32)
        np.maximum.at(out, hit, w)
    out[fresh] = 0.0
    return out
