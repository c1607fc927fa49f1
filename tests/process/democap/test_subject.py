"""The subject file: a subject's calibration written, read back, and refused when wrong."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mocaprig.errors import CalibrationError, ValidationError
from mocaprig.process.body import MARKER_NAMES
from mocaprig.process.body.shape import LENGTH_FIELDS, VERTICAL_CHAIN, BodyShape
from mocaprig.process.democap.solve import REFERENCE_HEIGHT_M, SHAPE_DIM, SubjectCalibration
from mocaprig.process.democap.subject import FORMAT, load_subject, save_subject


def _subject(seed: int = 0) -> SubjectCalibration:
    rng = np.random.default_rng(seed)
    return SubjectCalibration(
        shape_z=np.r_[1.04, 0.97, rng.normal(0.0, 0.03, SHAPE_DIM - 2)],
        marker_offsets_m=rng.normal(0.0, 0.01, (len(MARKER_NAMES), 3)),
        frames=40,
    )


def test_the_reference_body_has_the_reference_lengths_and_height() -> None:
    ref = BodyShape.from_height(REFERENCE_HEIGHT_M)
    cal = SubjectCalibration(
        shape_z=np.r_[1.0, 1.0, np.zeros(SHAPE_DIM - 2)],
        marker_offsets_m=np.zeros((len(MARKER_NAMES), 3)),
        frames=0,
    )
    assert cal.standing_height_m == pytest.approx(REFERENCE_HEIGHT_M, abs=1e-9)
    assert cal.segment_lengths_m == pytest.approx({k: getattr(ref, k) for k in LENGTH_FIELDS})


def test_lengths_give_back_the_shape_they_came_from() -> None:
    cal = _subject(1)
    again = SubjectCalibration.from_lengths(
        scale=cal.scale,
        girth=cal.girth,
        segment_lengths_m=cal.segment_lengths_m,
        marker_offsets_m=cal.marker_offsets_m,
        frames=cal.frames,
    )
    np.testing.assert_allclose(again.shape_z, cal.shape_z, atol=1e-12)
    chain = sum(cal.segment_lengths_m[k] for k in VERTICAL_CHAIN)
    assert cal.standing_height_m == pytest.approx(chain, abs=1e-9)


def test_a_subject_with_a_missing_length_or_a_bad_shape_is_refused() -> None:
    cal = _subject()
    lengths = dict(cal.segment_lengths_m)
    del lengths["forearm_length_m"]
    with pytest.raises(ValidationError, match=r"missing.*forearm_length_m"):
        SubjectCalibration.from_lengths(
            scale=1.0, girth=1.0, segment_lengths_m=lengths, marker_offsets_m=cal.marker_offsets_m,
            frames=1,
        )  # fmt: skip
    with pytest.raises(ValidationError, match="marker_offsets_m"):
        SubjectCalibration(shape_z=cal.shape_z, marker_offsets_m=np.zeros((52, 3)), frames=1)
    with pytest.raises(ValidationError, match="scale and girth"):
        SubjectCalibration(
            shape_z=np.r_[-1.0, cal.shape_z[1:]], marker_offsets_m=cal.marker_offsets_m, frames=1
        )


def test_a_saved_subject_reads_back_the_same_and_is_plain_json(tmp_path: Path) -> None:
    cal = _subject(2)
    path = save_subject(cal, tmp_path / "actor.json", source="rom.mcap: 40 of 300 instants")
    back = load_subject(path)
    np.testing.assert_allclose(back.shape_z, cal.shape_z, atol=1e-12)
    np.testing.assert_allclose(back.marker_offsets_m, cal.marker_offsets_m, atol=1e-12)
    assert back.frames == 40
    doc = json.loads(path.read_text())
    assert doc["format"] == FORMAT
    assert doc["source"] == "rom.mcap: 40 of 300 instants"
    assert list(doc["marker_offsets_mm"]) == list(MARKER_NAMES)
    assert doc["marker_offsets_mm"]["LFHD"] == pytest.approx(
        (cal.marker_offsets_m[MARKER_NAMES.index("LFHD")] * 1e3).tolist()
    )
    assert doc["standing_height_m"] == pytest.approx(cal.standing_height_m)
    assert not list(tmp_path.glob("*.part"))


def test_an_existing_subject_file_is_not_replaced_without_overwrite(tmp_path: Path) -> None:
    path = save_subject(_subject(0), tmp_path / "actor.json")
    before = path.read_bytes()
    with pytest.raises(CalibrationError, match=r"exists.*--overwrite"):
        save_subject(_subject(1), path)
    assert path.read_bytes() == before
    save_subject(_subject(1), path, overwrite=True)
    assert path.read_bytes() != before
    with pytest.raises(CalibrationError, match=r"\.json"):
        save_subject(_subject(0), tmp_path / "actor.vsk")


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda d: "{not json", "cannot be read"),
        (lambda d: {**d, "format": "something else"}, "not a subject file"),
        (lambda d: {**d, "format_version": 99}, "format_version 99"),
        (lambda d: {k: v for k, v in d.items() if k != "girth"}, "'girth' is missing"),
        (
            lambda d: {
                **d,
                "marker_offsets_mm": {
                    k: v for k, v in d["marker_offsets_mm"].items() if k != "RHEL"
                },
            },
            r"missing \['RHEL'\]",
        ),
        (
            lambda d: {
                **d,
                "segment_lengths_m": {**d["segment_lengths_m"], "shank_length_m": 0.5},
            },
            "standing_height_m .* disagrees",
        ),
        (
            lambda d: {**d, "segment_lengths_m": {**d["segment_lengths_m"], "hand_length_m": -0.1}},
            "must be > 0",
        ),
    ],
    ids=["not-json", "format", "version", "field", "marker", "height", "negative"],
)
def test_a_broken_subject_file_is_refused_naming_the_file(
    tmp_path: Path, edit: object, match: str
) -> None:
    path = save_subject(_subject(3), tmp_path / "actor.json")
    doc = edit(json.loads(path.read_text()))  # type: ignore[operator]
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    with pytest.raises(CalibrationError, match=match) as err:
        load_subject(path)
    assert str(path) in str(err.value)


def test_a_missing_subject_file_says_how_to_make_one(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="democap subject"):
        load_subject(tmp_path / "nobody.json")
