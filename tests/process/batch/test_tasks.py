"""``process.batch.tasks``: the real DeMoCap tasks on the shared calibrated session."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mocaprig.process.batch.sessions import SUBJECT_NAME, find_sessions
from mocaprig.process.batch.tasks import ProcessSettings, democap_plan_task, democap_span_task
from mocaprig.process.body import MARKER_NAMES
from mocaprig.process.democap.solve import SHAPE_DIM, SubjectCalibration
from mocaprig.process.democap.subject import save_subject
from tests.conftest import CalibratedSession


@pytest.mark.slow
def test_a_span_of_a_session_with_a_subject_file_is_solved_as_that_subject(
    calibrated_session: CalibratedSession, tmp_path: Path
) -> None:
    subject = SubjectCalibration(
        shape_z=np.r_[0.9, 1.0, np.zeros(SHAPE_DIM - 2)],
        marker_offsets_m=np.zeros((len(MARKER_NAMES), 3)),
        frames=3,
    )
    save_subject(subject, tmp_path / SUBJECT_NAME)
    (session,) = find_sessions([calibrated_session.session], calib=calibrated_session.calib)
    # the shared session's folder holds no subject file: point the session at ours
    as_actor = dataclasses.replace(session, subject=str(tmp_path / SUBJECT_NAME))
    plan = democap_plan_task(as_actor, ProcessSettings(methods=("democap",), democap_every=40))
    span = democap_span_task(as_actor, plan.span(0, 2))
    assert span.subject_height_m == pytest.approx(subject.standing_height_m)
    assert span.stop - span.start == 2
    alone = democap_span_task(session, plan.span(0, 2))
    assert alone.subject_height_m is None
