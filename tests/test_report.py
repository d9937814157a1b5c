"""HTML report: panels file, colour mapping, 3D view, and rendering in headless Chromium."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import plotly.offline
import pytest
import trimesh

from chisel.cli import main as cli_main
from chisel.core.errors import FormatVersionError, InvalidInputError
from chisel.core.geometry import Camera, look_at
from chisel.core.raycast import MeshRaycaster
from chisel.eval.metrics import (
    RoiBox,
)
from chisel.eval.report import (
    ReportMeshes,
    StepPanel,
    build_report_html,
    colorize_depth,
    decimate,
    depth_range_mm,
    mesh_figure,
    read_panels,
    write_panels,
    write_report,
)
from chisel.eval.tables import (
    METRIC_KEYS,
    assemble_table,
    tabulate_sweep,
    write_sweep_csv,
    write_table,
)

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
CAM = Camera.from_fov(64, 48, 70)


# ------------------------------------------------------------------------- fixtures


def _metrics() -> dict:
    def cell(mean: float) -> dict:
        c = {k: 0.1 for k in METRIC_KEYS}
        c.update(
            mean_mm=mean,
            std_mm=mean / 3,
            n_points=500,
            n_gt_in_box=520,
            mask_precision=None,
            mask_recall=None,
        )
        return c

    steps = [{"step": 0, "label": "", "methods": {"updated": cell(0.23)}}]
    for s in range(1, 4):
        steps.append(
            {
                "step": s,
                "label": "",
                "methods": {
                    "no_update": cell(1.5 * s),
                    "updated": cell(1.0 + 0.3 * s),
                    "depth_ablation": cell(0.8 + 0.2 * s),
                    "registration_ablation": cell(5.0 + s),
                },
            }
        )
    return assemble_table(steps, "report-test")


def _meshes() -> tuple[trimesh.Trimesh, trimesh.Trimesh, int]:
    """Preop sphere (r 12 mm) and an updated one with a 2 mm deep 'bite' pushed outwards."""
    preop = trimesh.creation.icosphere(subdivisions=4, radius=12.0)
    v = preop.vertices.copy()
    bite = v[:, 2] > 9.0  # the cap around +z
    v[bite] *= (12.0 + 2.0) / 12.0
    return preop, trimesh.Trimesh(v, preop.faces.copy(), process=False), int(bite.sum())


def _panels() -> list[StepPanel]:
    preop, updated, _ = _meshes()
    T = look_at([0, 0, 0], [0, 0.3, 1], up=[0, -1, 0])
    d_pre = MeshRaycaster.from_trimesh(preop).render_depth(CAM, T)
    d_up = MeshRaycaster.from_trimesh(updated).render_depth(CAM, T)
    rng = np.random.default_rng(0)
    rgb = np.zeros((*CAM.shape, 3), np.uint8)
    rgb[..., 0] = np.linspace(60, 220, CAM.width, dtype=np.uint8)[None]
    rgb[..., 1] = 90
    rgb[..., 2] = rng.integers(40, 80, CAM.shape, dtype=np.uint8)
    est = d_up + rng.normal(0, 0.2, d_up.shape).astype(np.float32)
    est[:3] = np.nan  # a band without estimate: shown black
    return [
        StepPanel(
            step=s,
            frame_index=7 * s,
            rgb=rgb,
            preop_depth_mm=d_pre,
            gt_depth_mm=d_up,
            estimated_depth_mm=est,
            updated_depth_mm=d_up,
            change_mask=(d_up - d_pre) > 1.0,
        )
        for s in (1, 3)
    ]


# ------------------------------------------------------------------------- panels


def test_panels_round_trip(tmp_path: Path) -> None:
    panels = _panels()
    path = write_panels(tmp_path / "panels.npz", panels)
    back = read_panels(path)
    assert len(back) == 2
    for a, b in zip(panels, back, strict=True):
        assert (a.step, a.frame_index) == (b.step, b.frame_index)
        for key, arr in a.images().items():
            np.testing.assert_array_equal(arr, b.images()[key])  # NaN positions included
    # Stored without pickle, depth 0 = invalid on disk.
    with np.load(path, allow_pickle=False) as z:
        assert z["estimated_depth_mm"][0, 0, 0] == 0.0
        assert str(z["format"]) == "endoscopic-chisel/panels"
    only_rgb = [StepPanel(1, 0, rgb=panels[0].rgb)]
    assert read_panels(write_panels(tmp_path / "rgb.npz", only_rgb))[0].gt_depth_mm is None


def test_panels_reject_bad_input(tmp_path: Path) -> None:
    p = _panels()[0]
    with pytest.raises(InvalidInputError, match="all or none"):
        write_panels(tmp_path / "x.npz", [p, StepPanel(2, 0, rgb=p.rgb)])
    with pytest.raises(InvalidInputError, match="differs in size"):
        write_panels(
            tmp_path / "x.npz", [StepPanel(1, 0, rgb=p.rgb), StepPanel(2, 0, rgb=p.rgb[:10])]
        )
    with pytest.raises(InvalidInputError, match="no panel"):
        write_panels(tmp_path / "x.npz", [])
    with pytest.raises(InvalidInputError, match="at least one image"):
        StepPanel(1, 0)
    with pytest.raises(InvalidInputError, match="uint8"):
        StepPanel(1, 0, rgb=p.rgb.astype(np.float32))
    with pytest.raises(InvalidInputError, match="bool"):
        StepPanel(1, 0, change_mask=p.change_mask.astype(np.uint8))
    with pytest.raises(InvalidInputError, match="float depth"):
        StepPanel(1, 0, gt_depth_mm=np.ones((4, 4), np.int32))
    with pytest.raises(InvalidInputError, match="panel's is"):
        StepPanel(1, 0, rgb=p.rgb, gt_depth_mm=np.ones((4, 4), np.float32))
    with pytest.raises(InvalidInputError, match=">= 0"):
        StepPanel(-1, 0, rgb=p.rgb)
    np.savez(tmp_path / "other.npz", format=np.array("something-else"), version=np.array(1))
    with pytest.raises(FormatVersionError, match="not a panels file"):
        read_panels(tmp_path / "other.npz")
    np.savez(tmp_path / "v9.npz", format=np.array("endoscopic-chisel/panels"), version=np.array(9))
    with pytest.raises(FormatVersionError, match="version 9"):
        read_panels(tmp_path / "v9.npz")
    with pytest.raises(InvalidInputError, match="missing"):
        read_panels(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(InvalidInputError, match="cannot read panels"):
        read_panels(tmp_path / "junk.npz")


def test_colorize_depth_shared_range() -> None:
    d = np.array([[10.0, 15.0, 20.0, np.nan]], np.float32)
    lo, hi = depth_range_mm([d, d + 1])
    assert 10.0 <= lo < 11.0 and 20.0 < hi <= 21.0
    rgb = colorize_depth(d, 10.0, 20.0)
    assert rgb.dtype == np.uint8 and rgb.shape == (1, 4, 3)
    assert rgb[0, 3].tolist() == [0, 0, 0]  # no surface = black
    lum = rgb[0, :3].astype(int).sum(axis=1)
    assert lum[0] < lum[1] < lum[2]  # viridis: near = dark, far = bright
    assert depth_range_mm([np.full((2, 2), np.nan, np.float32)]) == (0.0, 1.0)


# ------------------------------------------------------------------------- 3D view


def test_decimate_and_highlight_removed_region() -> None:
    preop, updated, n_bite = _meshes()
    v, f = decimate(updated, 500)
    assert len(f) <= 500 and v.dtype == np.float32 and f.max() < len(v)
    fig = mesh_figure(
        ReportMeshes(preop, updated, max_faces=10_000, roi_box=RoiBox([-5, -5, 8], [5, 5, 15]))
    )
    up = fig.data[1]
    # Undecimated (the sphere has 5120 faces): exactly the bite's vertices are > 0.5 mm away.
    assert int(np.count_nonzero(np.asarray(up.intensity) > 0.5)) == n_bite
    assert f"({n_bite} vertices > 0.5 mm)" in up.name
    assert fig.data[2].name == "ROI box"
    with pytest.raises(InvalidInputError, match="non-empty"):
        ReportMeshes(trimesh.Trimesh(), updated)
    with pytest.raises(InvalidInputError, match="removed_threshold_mm"):
        ReportMeshes(preop, updated, removed_threshold_mm=0.0)
    with pytest.raises(InvalidInputError, match="max_faces"):
        ReportMeshes(preop, updated, max_faces=5)


def test_report_is_self_contained_and_deterministic() -> None:
    preop, updated, _ = _meshes()
    meshes = ReportMeshes(preop, updated)
    a = build_report_html(_metrics(), _panels(), meshes, None, "t")
    assert a == build_report_html(_metrics(), _panels(), meshes, None, "t")
    # No network: no external script, stylesheet, image or font outside the plotly.js
    # bundle (whose strings hold links such as the plotly logo's).
    bundle = plotly.offline.get_plotlyjs()
    assert a.count(bundle) == 1
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", a.replace(bundle, ""))
    assert "<link" not in a
    assert (
        a.replace(bundle, "").count("data:image/png;base64,") == 2 * 6 + 2
    )  # 6 images + colour bar per panel
    with pytest.raises(InvalidInputError, match="metrics"):
        build_report_html({"format": "x"}, [], None, None)


# ------------------------------------------------------------------------- Chromium


def _open_in_chromium(html_path: Path, screenshot: Path, profile: Path) -> tuple[list[dict], dict]:
    """Load the page headless; return (browser console log, page facts)."""
    pytest.importorskip("selenium", reason="selenium missing: run scripts/setup.sh (dev extras)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.support.ui import WebDriverWait

    if not Path(CHROMEDRIVER).is_file():
        pytest.fail(
            f"chromium is installed but {CHROMEDRIVER} is not: apt-get install chromium-driver"
        )
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in (
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
        "--enable-unsafe-swiftshader",  # software WebGL for the plotly 3D view
        f"--user-data-dir={profile}",
        "--window-size=1400,1000",
    ):
        opts.add_argument(flag)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    try:
        driver.set_page_load_timeout(120)
        driver.get(html_path.resolve().as_uri())
        # Every plotly figure of the report is a div with an id "fig-...".
        n_plots = len(
            re.findall(r'<div id="fig-[^"]+" class="plotly-graph-div"', html_path.read_text())
        )
        WebDriverWait(driver, 120).until(
            lambda d: (
                d.execute_script(
                    "return Array.from(document.querySelectorAll('.js-plotly-plot'))"
                    ".filter(e => e._fullLayout).length"
                )
                == n_plots
            )
        )
        facts = driver.execute_script(
            """
            const imgs = Array.from(document.images);
            return {
              plots: document.querySelectorAll('.js-plotly-plot').length,
              svg_traces: document.querySelectorAll('#fig-error-vs-step .scatterlayer .trace').length,
              gl_canvas: document.querySelectorAll('#fig-meshes canvas').length,
              images: imgs.length,
              broken_images: imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length,
              table_rows: document.querySelectorAll('#main-table tr').length,
              external: performance.getEntriesByType('resource').map(r => r.name)
                .filter(n => !n.startsWith('data:')),
              height: document.body.scrollHeight,
            };
            """
        )
        driver.set_window_size(1400, min(int(facts["height"]) + 400, 8000))
        driver.save_screenshot(str(screenshot))
        return driver.get_log("browser"), facts
    finally:
        driver.quit()


def test_report_renders_in_chromium(tmp_path: Path) -> None:
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"{CHROMIUM} is not installed (scripts/setup.sh installs it)")
    preop, updated, _ = _meshes()
    sweeps = {}
    for name, param in (("sequence length", "frames"), ("pose noise", "pose_noise_mm")):
        runs = [(v, _metrics()) for v in (10.0, 30.0, 50.0)]
        sweeps[name] = tabulate_sweep(param, runs)
    out = write_report(
        tmp_path / "report.html",
        _metrics(),
        _panels(),
        ReportMeshes(preop, updated, roi_box=RoiBox([-5, -5, 8], [5, 5, 15])),
        sweeps,
        title="Report test",
    )
    assert out.stat().st_size < 15 * 2**20
    logs, facts = _open_in_chromium(out, tmp_path / "report.png", tmp_path / "profile")
    errors = [e for e in logs if e["level"] == "SEVERE"]
    assert not errors, errors
    assert facts["plots"] == 4 and facts["svg_traces"] == 4 and facts["gl_canvas"] >= 1
    assert facts["images"] == 14 and facts["broken_images"] == 0
    assert facts["table_rows"] == 5  # header + preop + 3 bites
    assert facts["external"] == []  # the page fetched nothing from outside itself
    assert (tmp_path / "report.png").stat().st_size > 10_000


def test_cli_report(tmp_path: Path) -> None:
    preop, updated, _ = _meshes()
    preop.export(tmp_path / "preop.ply")
    updated.export(tmp_path / "updated.ply")
    write_table(tmp_path, _metrics())
    write_panels(tmp_path / "panels.npz", _panels())
    write_sweep_csv(
        tmp_path / "sweep.csv", tabulate_sweep("frames", [(10.0, _metrics()), (30.0, _metrics())])
    )
    base = ["report", "--metrics", str(tmp_path / "metrics.json"), "--out"]
    rc = cli_main(
        [
            *base,
            str(tmp_path / "r.html"),
            "--panels",
            str(tmp_path / "panels.npz"),
            "--preop-mesh",
            str(tmp_path / "preop.ply"),
            "--updated-mesh",
            str(tmp_path / "updated.ply"),
            "--roi=-5,-5,8,5,5,15",
            "--sweep",
            f"seqlen={tmp_path / 'sweep.csv'}",
        ]
    )
    assert rc == 0
    text = (tmp_path / "r.html").read_text()
    assert 'id="fig-meshes"' in text and 'id="fig-sweep-0"' in text and "bite 3, frame 21" in text
    assert cli_main([*base, str(tmp_path / "m.html")]) == 0  # metrics only
    assert (
        cli_main([*base, str(tmp_path / "bad.html"), "--preop-mesh", str(tmp_path / "preop.ply")])
        == 1
    )
    assert cli_main([*base, str(tmp_path / "bad.html"), "--sweep", "nonsense"]) == 1
    assert not (tmp_path / "bad.html").exists()


def test_chromium_harness_catches_console_errors(tmp_path: Path) -> None:
    # The check above must be able to fail: a script error in the page shows up as SEVERE.
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"{CHROMIUM} is not installed (scripts/setup.sh installs it)")
    page = write_report(tmp_path / "r.html", _metrics())
    page.write_text(page.read_text().replace("</body>", "<script>undefinedFn();</script></body>"))
    logs, facts = _open_in_chromium(page, tmp_path / "r.png", tmp_path / "profile")
    assert facts["plots"] == 1
    assert any(e["level"] == "SEVERE" and "undefinedFn" in e["message"] for e in logs)


# ------------------------------------------------------------------------- updated-CT slices

MARKER_HU = 1500.0  # brighter than anything else in the synthetic CT: white, and unique


def _ct_case(flip: bool):
    """A tiny HU CT (1 mm voxels), a 5^3 tissue block that a step removes (plus one voxel
    in the block's centre row so the slices cut there), a method that removed part of it,
    and marker voxels: patient's left (+x), anterior (-y) and superior (+z) of the block.

    flip: voxel axes i, j run towards the patient's right and front (an RAS-ordered file)."""
    from chisel.io.ct import CtVolume

    shape = (30, 26, 24)
    T = np.eye(4)
    if flip:
        T[:3, :3] = np.diag([-1.0, -1.0, 1.0])
        T[:3, 3] = [shape[0] - 1, shape[1] - 1, 0]
    T[:3, 3] += [-10.0, 5.0, -3.0]
    world_c = np.array([5.0, 18.0, 9.0])  # block centre, LPS mm

    def vox(p):
        return tuple(int(v) for v in np.rint(np.linalg.solve(T, [*p, 1.0])[:3]))

    hu = np.full(shape, -1000.0, np.float32)
    c = np.array(vox(world_c))
    hu[c[0] - 5 : c[0] + 6, c[1] - 5 : c[1] + 6, c[2] - 5 : c[2] + 6] = 40.0  # soft tissue
    block = np.zeros(shape, bool)
    block[c[0] - 2 : c[0] + 3, c[1] - 2 : c[1] + 3, c[2] - 2 : c[2] + 3] = True
    block[vox(world_c + [3.0, 0, 0])] = True  # the centre row: the most voxels at y_c, z_c
    hu[block] = 700.0  # bone, so that the removed region is obvious before
    markers = {
        "left": world_c + [8.0, 0.0, 0.0],
        "anterior": world_c + [0.0, -8.0, 0.0],
        "superior": world_c + [0.0, 0.0, 8.0],
    }
    for p in markers.values():
        hu[vox(p)] = MARKER_HU
    before = CtVolume(hu, T, "intensity")
    truth = CtVolume((hu > -480).astype(np.uint8) * ~block, T, "label")
    part = block.copy()
    part[: c[0], :, :] = False  # the method removed only the half at larger i
    upd = hu.copy()
    upd[part] = -1000.0
    box = RoiBox(world_c - 6.0, world_c + 6.0)
    return before, CtVolume(upd, T, "intensity"), truth, box, part, markers, world_c


def _decode_png(uri: str) -> np.ndarray:
    import base64

    import cv2

    buf = np.frombuffer(base64.b64decode(uri.split(",", 1)[1]), np.uint8)
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _slice_pngs(text: str) -> dict[tuple[str, str], np.ndarray]:
    found = re.findall(
        r"data-plane='(\w+)' data-name='([\w ]+)' src='(data:image/png;base64,[^']+)'", text
    )
    return {(plane, name): _decode_png(uri) for plane, name, uri in found}


def _pixel_world(s, rc) -> np.ndarray:
    r, c = rc
    return (s.T_world_from_pixel @ [c, r, 0.0, 1.0])[:3]


@pytest.mark.parametrize("flip", [False, True], ids=["lps-ordered", "ras-ordered"])
def test_ct_slices_orientation_outline_and_dice(flip: bool) -> None:
    from chisel.ct_export import removed_region_scores
    from chisel.eval.ct_slices import UPSCALE, make_ct_slices, window_grey

    before, upd, truth, box, part, markers, world_c = _ct_case(flip)
    dice = removed_region_scores(before, upd, truth)["dice"]
    assert 0.3 < dice < 0.9
    axial, coronal = make_ct_slices(
        2, before, {"updated": upd}, box, truth_label=truth, dice={"updated": dice}
    )
    assert (axial.plane, coronal.plane) == ("axial", "coronal")
    assert axial.position_mm == pytest.approx(world_c[2])  # through the most removed voxels
    assert coronal.position_mm == pytest.approx(world_c[1])
    html_text = build_report_html(_metrics(), ct_slices=[axial, coronal])
    pngs = _slice_pngs(html_text)
    assert set(pngs) == {
        (p, n) for p in ("axial", "coronal") for n in ("preoperative", "truth", "updated")
    }
    assert f"updated-CT Dice <b>{dice:.3f}</b>" in html_text and "W 2000 / L 0 HU" in html_text
    k = UPSCALE
    for s in (axial, coronal):
        hu = s.images["preoperative"]
        h, w = hu.shape
        # every marker in the plane sits where radiologists expect it (PNG decoded)
        png = pngs[(s.plane, "preoperative")]
        assert png.shape == (h * k, w * k, 3)
        white = np.argwhere(np.all(png == 255, axis=2)) // k
        for rc in np.unique(white, axis=0):
            p = _pixel_world(s, rc)
            name = min(markers, key=lambda n: np.linalg.norm(markers[n] - p))
            assert np.linalg.norm(markers[name] - p) < 0.6, (s.plane, rc, p)
            if name == "left":  # the patient's left on the image's right
                assert rc[1] > w / 2 + 3 and abs(rc[0] - np.argwhere(hu > 600)[:, 0].mean()) < 3
            if name == "anterior":
                assert s.plane == "axial" and rc[0] < h / 2 - 3  # anterior up
            if name == "superior":
                assert s.plane == "coronal" and rc[0] < h / 2 - 3  # superior up
        seen = {
            min(markers, key=lambda n: np.linalg.norm(markers[n] - _pixel_world(s, rc)))
            for rc in np.unique(white, axis=0)
        }
        assert seen == ({"left", "anterior"} if s.plane == "axial" else {"left", "superior"})
        # the method's removed pixels are exactly its removed voxels in the plane
        removed = s.removed["updated"]
        ijk = np.argwhere(part)
        wv = ijk @ before.T_world_from_voxel[:3, :3].T + before.T_world_from_voxel[:3, 3]
        axis = 2 if s.plane == "axial" else 1
        in_plane = wv[np.isclose(wv[:, axis], s.position_mm)]
        assert removed.sum() == len(in_plane) > 0
        for rc in np.argwhere(removed):
            assert np.min(np.linalg.norm(in_plane - _pixel_world(s, rc), axis=1)) < 1e-6
        # the red outline is the inner edge of those pixels, the green one rings the truth
        png = pngs[(s.plane, "updated")]
        red = np.all(png == (255, 40, 40), axis=2)
        up = np.kron(removed, np.ones((k, k), bool))
        assert red.any() and np.all(up[red])
        assert np.array_equal(np.argwhere(red).min(0), np.argwhere(up).min(0))
        assert np.array_equal(np.argwhere(red).max(0), np.argwhere(up).max(0))
        green = np.all(png == (40, 220, 40), axis=2)
        true_up = np.kron(s.removed["truth"], np.ones((k, k), bool))
        assert green.any() and not np.any(true_up[green])
        assert np.array_equal(np.argwhere(green).min(0), np.argwhere(true_up).min(0) - 1)
        # grey window W 2000 / L 0: air black, soft tissue mid grey, 1000 HU and above white
        assert window_grey(np.array([-1000.0, 0.0, 40.0, 1000.0])).tolist() == [0, 128, 133, 255]
        # the updated image shows air where the method removed tissue
        assert np.all(s.images["updated"][removed] == -1000.0)
        assert np.all(s.images["preoperative"][removed] == 700.0)


def test_ct_slices_file_round_trip_and_cli(tmp_path: Path) -> None:
    from chisel.eval.ct_slices import make_ct_slices, read_ct_slices, write_ct_slices

    before, upd, truth, box, *_ = _ct_case(False)
    slices = make_ct_slices(
        1,
        before,
        {"updated": upd, "no_update": before},
        box,
        truth_label=truth,
        dice={"updated": 0.5, "no_update": 0.0},
    )
    path = write_ct_slices(tmp_path / "step_01_slices.npz", slices)
    back = read_ct_slices(path)
    assert [(s.step, s.plane, s.methods) for s in back] == [
        (1, p, ["updated", "no_update"]) for p in ("axial", "coronal")
    ]
    for a, b in zip(slices, back, strict=True):
        assert a.dice == b.dice and a.position_mm == b.position_mm
        np.testing.assert_array_equal(a.T_world_from_pixel, b.T_world_from_pixel)
        for name in a.images:
            np.testing.assert_array_equal(a.images[name], b.images[name])
        assert set(a.removed) == set(b.removed) == {"updated", "no_update", "truth"}
        for name in a.removed:
            np.testing.assert_array_equal(a.removed[name], b.removed[name])
    np.savez(tmp_path / "bad.npz", meta=np.array('{"format": "x"}'))
    with pytest.raises(FormatVersionError):
        read_ct_slices(tmp_path / "bad.npz")
    with pytest.raises(InvalidInputError, match="missing"):
        read_ct_slices(tmp_path / "none.npz")
    with pytest.raises(InvalidInputError, match="grid"):
        make_ct_slices(
            1,
            before,
            {"updated": truth.__class__(upd.data[1:], upd.T_world_from_voxel, "intensity")},
            box,
        )
    write_table(tmp_path, _metrics())
    out = tmp_path / "r.html"
    rc = cli_main(
        [
            "report",
            "--metrics",
            str(tmp_path / "metrics.json"),
            "--out",
            str(out),
            "--ct-slices",
            str(path),
        ]
    )
    assert rc == 0
    text = out.read_text()
    assert "Updated CT through the change box" in text
    assert len(_slice_pngs(text)) == 2 * 4  # preop, truth, two methods; two planes
