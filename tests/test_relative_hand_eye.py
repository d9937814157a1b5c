"""UpdateConfig.relative_hand_eye: a relative estimate's frames placed by the step's
hand-eye correction ("step") or each by its own registration ("frame")."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import test_updater_scenes as sc

from chisel.batch import update_step
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import rotation_angle_deg
from chisel.depth_source import CallableDepth, GroundTruthDepth
from chisel.detect import Detection, HandEye
from chisel.update_config import UpdateConfig


@pytest.fixture(scope="module")
def step_inputs() -> dict:
    return sc.hand_eye_step()


def test_each_frame_undoes_the_hand_eye_error_on_its_own(step_inputs: dict) -> None:
    s = step_inputs
    relative = CallableDepth(lambda f: f.depth_mm * 0.037)
    cfg = UpdateConfig(relative_hand_eye="frame")
    _, rep = update_step(s["model"], s["cam"], s["frames"], relative, cfg)
    assert "not_applied" in rep.sequence_registration
    # The step's F is still estimated and reported, and is right (exact depth).
    F = np.array(rep.sequence_registration["hand_eye"]["T_cam_from_corrected_cam"])
    assert rotation_angle_deg(F @ s["E"]) < 0.2
    left = []
    for T, f in zip(s["tracked"], rep.to_dict()["frames"], strict=True):
        reg = f["registration"] or {}
        if reg.get("ok") and "rejected" not in reg:
            # The frame's camera-side correction, against the error it was given.
            C = np.linalg.inv(T) @ np.array(reg["T_model_from_est"]) @ T
            left.append(rotation_angle_deg(C @ s["E"]))
    assert len(left) >= 9 and np.median(left) < 0.3


def test_the_step_correction_places_every_frame_by_default(step_inputs: dict) -> None:
    s = step_inputs
    relative = CallableDepth(lambda f: f.depth_mm * 0.037)
    _, rep = update_step(s["model"], s["cam"], s["frames"], relative)
    assert "not_applied" not in rep.sequence_registration
    assert "rejected" not in rep.sequence_registration
    F = np.array(rep.sequence_registration["hand_eye"]["T_cam_from_corrected_cam"])
    assert rotation_angle_deg(F @ s["E"]) < 0.2


def _learnt_frames(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The indices of the detections the step's running hand-eye estimate learns from."""
    learnt: list[int] = []
    learn = HandEye.learn

    def spy(self: HandEye, det: Detection) -> None:
        learnt.append(det.index)
        learn(self, det)

    monkeypatch.setattr(HandEye, "learn", spy)
    return learnt


def test_a_frame_with_an_instrument_in_view_registers_but_does_not_teach(
    step_inputs: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    s = step_inputs
    h, w = s["cam"].shape
    tool = np.ones((h, w), dtype=bool)
    tool[h // 3 :, w // 3 : 2 * w // 3] = False  # an instrument from the bottom edge
    held = {3, 4, 5}  # a tool episode: consecutive frames
    frames = [replace(f, mask=tool) if f.index in held else f for f in s["frames"]]
    relative = CallableDepth(lambda f: f.depth_mm * 0.037)
    learnt = _learnt_frames(monkeypatch)
    cfg = UpdateConfig(relative_hand_eye="frame")
    _, rep = update_step(s["model"], s["cam"], frames, relative, cfg)
    assert sorted(learnt) == sorted(set(range(len(frames))) - held)
    regs = {f["index"]: f["registration"] or {} for f in rep.to_dict()["frames"]}
    assert all(regs[i].get("ok") for i in held)
    # Without instruments every frame teaches.
    learnt.clear()
    update_step(s["model"], s["cam"], s["frames"], relative, cfg)
    assert sorted(learnt) == list(range(len(frames)))


def test_metric_depth_keeps_the_step_correction(step_inputs: dict) -> None:
    s = step_inputs
    cfg = UpdateConfig(relative_hand_eye="frame")
    _, rep = update_step(s["model"], s["cam"], s["frames"], GroundTruthDepth(), cfg)
    assert "not_applied" not in rep.sequence_registration


def test_an_unknown_mode_is_named() -> None:
    with pytest.raises(InvalidInputError, match="relative_hand_eye"):
        UpdateConfig(relative_hand_eye="both")  # type: ignore[arg-type]
