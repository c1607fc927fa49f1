"""ECD-layout takes: the reader, and EventCap's tracking on a real DAVIS recording."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from mocaprig.errors import RecordingError
from mocaprig.process.eventcap.ecd import read_ecd_take
from mocaprig.process.eventcap.edi import EdiBatch
from mocaprig.process.eventcap.tracking import track_frames


def _write_folder(root: Path, *, frames_txt: str | None = None) -> None:
    root.mkdir()
    (root / "events.txt").write_text("0.000100 1 2 1\n0.000200 3 4 0\n", encoding="utf-8")
    (root / "images").mkdir()
    for k in range(2):
        cv2.imwrite(str(root / "images" / f"frame_{k}.png"), np.full((6, 8), 10 * k, np.uint8))
    (root / "images.txt").write_text(
        "0.001000 images/frame_0.png\n0.041000 images/frame_1.png\n", encoding="utf-8"
    )
    if frames_txt is not None:
        (root / "frames.txt").write_text(frames_txt, encoding="utf-8")


def test_ecd_folder_without_exposures_gives_frames_at_their_times(tmp_path: Path) -> None:
    _write_folder(tmp_path / "take")
    take = read_ecd_take(tmp_path / "take")
    assert take.shape_hw == (6, 8)
    assert not take.exposure_known
    assert [f.t_us for f in take.frames] == [1000, 41000]
    assert take.frames[0].exposure_start_us == take.frames[0].exposure_end_us == 1000
    np.testing.assert_array_equal(take.events["t"], [100, 200])
    assert take.frames[1].image_dn[0, 0] == 10.0


def test_ecd_folder_with_frames_txt_gives_the_real_exposure_windows(tmp_path: Path) -> None:
    rows = "# index t begin end fb fe\n0 0.001 0.0008 0.0012 0 0.01\n1 0.041 0.0408 0.0412 0 0.05\n"
    _write_folder(tmp_path / "take", frames_txt=rows)
    take = read_ecd_take(tmp_path / "take")
    assert take.exposure_known
    assert (take.frames[1].exposure_start_us, take.frames[1].exposure_end_us) == (40800, 41200)


def test_ecd_reader_names_what_is_missing_or_malformed(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match=r"no events\.txt"):
        read_ecd_take(tmp_path)
    _write_folder(tmp_path / "bad", frames_txt="0 0.001 0.0008 0.0012\n")
    with pytest.raises(RecordingError, match="expected 2 rows"):
        read_ecd_take(tmp_path / "bad")
    _write_folder(tmp_path / "missing")
    (tmp_path / "missing" / "images" / "frame_1.png").unlink()
    with pytest.raises(RecordingError, match=r"frame_1\.png"):
        read_ecd_take(tmp_path / "missing")


def test_tracks_on_a_real_davis346_recording_agree_forward_and_backward(
    shared_data: Path,
) -> None:
    # No ground truth: the frames are sharp and the camera still, so this checks consistency.
    # Between pairs of APS frames 40 ms apart (cars driving past), features on the moving
    # regions are tracked forward from one frame and backward from the next on EDI latent
    # images; most are found both ways and the two halves meet at mid-batch.
    take = read_ecd_take(shared_data / "events" / "davis346_icns_street" / "ecd_export")
    assert take.shape_hw == (260, 346)
    ev = take.events
    t0 = min(int(ev["t"].min()), take.frames[0].exposure_start_us)
    t1 = max(int(ev["t"].max()), take.frames[-1].exposure_end_us)
    edi = EdiBatch(ev, shape_hw=take.shape_hw, t_start_us=t0, t_end_us=t1)
    stitched_share, gaps = [], []
    for k in (10, 20, 30, 40):
        a, b = take.frames[k], take.frames[k + 1]
        c = edi.fit_contrast(
            a.image_dn,
            b.image_dn,
            exposure_a_us=(a.exposure_start_us, a.exposure_end_us),
            exposure_b_us=(b.exposure_start_us, b.exposure_end_us),
            saturation_dn=255,
        ).c_on
        sharp = [
            edi.deblur(
                f.image_dn,
                exposure_start_us=f.exposure_start_us,
                exposure_end_us=f.exposure_end_us,
                t_ref_us=f.t_us,
                c_on=c,
                c_off=c,
                saturation_dn=255.0,
            )
            for f in (a, b)
        ]
        times = np.arange(a.t_us, b.t_us + 1, 1000)
        w = ((times - times[0]) / (times[-1] - times[0]))[:, None, None]
        latent = (1 - w) * edi.latent_log_images(sharp[0], times) + w * edi.latent_log_images(
            sharp[1], times
        )
        on_a, off_a = edi.polarity_counts(a.t_us)
        on_b, off_b = edi.polarity_counts(b.t_us)
        active = ((on_b - on_a) + (off_b - off_a)) > 0
        mask = cv2.dilate(active.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        res = track_frames(times, latent, mask_t0=mask, mask_t1=mask)
        kinds = [tr.kind for tr in res.trajectories]
        stitched_share.append(kinds.count("stitched") / max(len(kinds), 1))
        mid = (a.t_us + b.t_us) // 2
        for tr in res.trajectories:
            if tr.kind != "stitched":
                continue
            f, bw = res.forward[tr.forward_id], res.backward[tr.backward_id]
            if mid in f.t_us and mid in bw.t_us:
                gaps.append(
                    np.linalg.norm(
                        f.xy_px[list(f.t_us).index(mid)] - bw.xy_px[list(bw.t_us).index(mid)]
                    )
                )
    # Measured: 52–68 % of trajectories stitched, forward and backward 0.51–0.55 px apart at
    # mid-batch (median per pair), 11–13 stitched trajectories per pair.
    assert np.mean(stitched_share) > 0.4
    assert len(gaps) >= 30
    assert np.median(gaps) < 1.0
