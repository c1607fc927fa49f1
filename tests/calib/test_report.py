"""The calibration report's pieces: the rig in 3D (frusta, the markers' volume) and its page.

The whole report of a real calibration is written by ``calibrate vicon --report`` in
``tests/calib/test_commands_calibrate.py`` and ``tests/test_progress_commands.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocaprig.calib.calibration import CameraCalibration
from mocaprig.calib.camera_model import project_points
from mocaprig.calib.report_html import index_html, write_index
from mocaprig.calib.report_rig import frustum_corners_m, marker_volume_m, write_rig_figure
from mocaprig.errors import CalibrationError

_PNG = b"\x89PNG\r\n\x1a\n"


def _camera(
    name: str = "d415/1", *, centre_m: tuple[float, float, float] = (2.0, -1.0, 1.5)
) -> CameraCalibration:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [-100.0, 5.0, 30.0], degrees=True).as_matrix()
    T[:3, 3] = centre_m
    return CameraCalibration(
        name=name,
        kind="d415",
        serial=name.split("/")[-1],
        width=848,
        height=480,
        K=np.array([[425.0, 0.0, 421.0], [0.0, 424.0, 238.0], [0.0, 0.0, 1.0]]),
        distortion=np.array([0.08, -0.12, 0.001, -0.002, 0.03]),
        T_world_cam=T,
    )


def test_frustum_corners_project_back_onto_the_image_corners_at_their_depth() -> None:
    cam = _camera()
    corners = frustum_corners_m(cam, 1.7)
    uv, z = project_points(corners, cam.T_world_cam, cam.K, cam.distortion)
    expected = [[0, 0], [848, 0], [848, 480], [0, 480]]
    np.testing.assert_allclose(uv, expected, atol=0.05)
    np.testing.assert_allclose(z, 1.7, rtol=1e-12)


def test_frustum_refuses_a_depth_that_is_not_positive() -> None:
    with pytest.raises(CalibrationError, match=r"d415/1.*frustum depth must be > 0"):
        frustum_corners_m(_camera(), 0.0)


def test_marker_volume_spans_the_finite_samples_and_is_none_without_any() -> None:
    p = np.array([[[0.0, 1.0, 2.0], [np.nan, 9.0, 9.0]], [[-1.0, 3.0, 0.5], [1.0, 2.0, np.inf]]])
    low, high = marker_volume_m(p)  # type: ignore[misc]
    np.testing.assert_array_equal(low, [-1.0, 1.0, 0.5])
    np.testing.assert_array_equal(high, [0.0, 3.0, 2.0])
    assert marker_volume_m(np.full((3, 2, 3), np.nan)) is None


def test_rig_figure_is_written_with_cameras_and_markers(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    static = rng.normal([0.0, 0.0, 1.0], 0.3, (40, 3))
    trial = static + rng.normal(0.0, 0.2, (50, 1, 3))
    trial[3, 5] = np.nan
    cams = [_camera("d415/1"), _camera("d415/2", centre_m=(-2.0, 1.0, 1.4))]
    path = write_rig_figure(
        cams, tmp_path / "rig.png", static_markers_m=static, trial_markers_m=trial
    )
    assert path.read_bytes()[:8] == _PNG


def test_rig_figure_refuses_nothing_to_draw(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="no camera and no finite Vicon marker"):
        write_rig_figure([], tmp_path / "rig.png", static_markers_m=np.full((3, 3), np.nan))
    assert not (tmp_path / "rig.png").exists()


def test_index_page_shows_the_figures_in_order_beside_the_escaped_summary() -> None:
    page = index_html(
        title="Vicon <calibration>",
        figures=[("rig_3d.png", "the rig"), ("clocks.png", "clock fits & residuals")],
        summary={"note": "a < b", "rms_px": np.float64(0.25)},
        summary_file="summary.json",
        notes=["camera 'x' & y"],
    )
    assert page.index('src="rig_3d.png"') < page.index('src="clocks.png"')
    assert "<title>Vicon &lt;calibration&gt;</title>" in page
    assert "clock fits &amp; residuals" in page
    assert "a &lt; b" in page
    assert '"rms_px": 0.25' in page
    assert "camera &#x27;x&#x27; &amp; y" in page
    assert "<script" not in page


def test_write_index_writes_the_summary_json_and_the_page(tmp_path: Path) -> None:
    fig = tmp_path / "a.png"
    fig.write_bytes(_PNG)
    summary_path, page = write_index(
        tmp_path, title="t", figures=[(fig, "a")], summary={"cameras": [{"rms": np.float32(0.5)}]}
    )
    assert json.loads(summary_path.read_text(encoding="utf-8")) == {"cameras": [{"rms": 0.5}]}
    assert 'href="summary.json"' in page.read_text(encoding="utf-8")


def test_write_index_refuses_a_figure_outside_the_report_folder(tmp_path: Path) -> None:
    (tmp_path / "report").mkdir()
    with pytest.raises(CalibrationError, match=r"not in the report folder .*report"):
        write_index(tmp_path / "report", title="t", figures=[(tmp_path / "a.png", "a")], summary={})
