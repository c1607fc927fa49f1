"""Foxglove layouts (issue 18, item 2): each stored layout opens its panels on a file of its kind
made by our own writers, checked against the file's channels and schemas as stored (read with
the mcap package, not our reader), and ``mocaprig info FILE --layout`` writes the right one."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool  # type: ignore[import-untyped]
from mcap.reader import make_reader

from mocaprig.acquire.layout import (
    LAYOUT_USES,
    LayoutUse,
    choose_use,
    layout_for,
    layout_problems,
    layout_template,
    write_layout,
)
from mocaprig.cli import main
from mocaprig.errors import ValidationError

D415_A, D415_B, DAVIS = "874922473674", "888849880075", "02463973"


# --------------------------------------------------------------------------------------------
# files of each kind, made by our writers (small)


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[LayoutUse, Path]:
    from mocaprig.acquire.commands_record import record
    from mocaprig.calib.calibration import Calibration
    from mocaprig.calib.calibration_attachment import attach_calibration
    from mocaprig.process.body import DEMOCAP_JOINTS, MARKER_NAMES
    from mocaprig.process.body.kinematics import (
        eventcap_keypoints,
        forward_kinematics,
        neutral_pose,
    )
    from mocaprig.process.body.shape import BodyShape
    from mocaprig.process.democap.replay import ReplayResult, write_scene_mcap
    from mocaprig.process.eventcap.run import EventcapResultsWriter, ResultsHeader

    d = tmp_path_factory.mktemp("layouts")
    rec = d / "session.mcap"
    assert record(out=rec, seconds=0.3, mock=True, rig=None, cameras=2) == 0
    calibrated = attach_calibration(rec, d / "calibrated.mcap", Calibration(cameras=(), clocks=()))

    rng = np.random.default_rng(0)
    n = 3
    t_ref = 5_000_000_000 + 33_333_333 * np.arange(n, dtype=np.int64)
    replay = ReplayResult(
        session=rec,
        outputs={},
        cameras=(f"d415/{D415_A}",),
        frames_per_camera={f"d415/{D415_A}": n},
        t_ref_ns=t_ref,
        cameras_per_instant=np.ones(n, dtype=np.int64),
        points_per_instant=np.full(n, 40, dtype=np.int64),
        markers_m=rng.normal(size=(n, len(MARKER_NAMES), 3)),
        joints_m=rng.normal(size=(n, len(DEMOCAP_JOINTS), 3)),
    )
    clouds = [rng.normal(size=(40, 3)) for _ in range(n)]
    democap = write_scene_mcap(replay, d / "democap.mcap", clouds=clouds)

    shape = BodyShape.from_height(1.75)
    poses = np.repeat(neutral_pose(shape)[None], n, axis=0)
    t_us = 20_000 + 1000 * np.arange(n, dtype=np.int64)
    header = ResultsHeader(
        session=rec,
        davis=f"davis/{DAVIS}",
        batches=1,
        frames=n,
        time_base="vicon",
        t_first_davis_us=int(t_us[0]),
        world_frame="vicon",
    )
    eventcap = d / "eventcap.mcap"
    with EventcapResultsWriter(header, shape, mcap=eventcap) as writer:
        kp = eventcap_keypoints(forward_kinematics(poses, shape), shape)
        writer.write(t_us * 1000, poses, kp)
    return {"recording": rec, "calibration": calibrated, "democap": democap, "eventcap": eventcap}


def _channels(path: Path) -> tuple[dict[str, str], dict[str, str], dict[str, Any]]:
    """``(topic -> schema name, topic -> frame_id, topic -> message descriptor)`` as stored."""
    schemas, frames, descs = {}, {}, {}
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    for ch in summary.channels.values():
        sch = summary.schemas[ch.schema_id]
        schemas[ch.topic] = sch.name
        if "frame_id" in ch.metadata:
            frames[ch.topic] = ch.metadata["frame_id"]
        pool = descriptor_pool.DescriptorPool()
        for fdp in descriptor_pb2.FileDescriptorSet.FromString(sch.data).file:
            pool.Add(fdp)
        descs[ch.topic] = pool.FindMessageTypeByName(sch.name)
    return schemas, frames, descs


_PANEL_SCHEMAS = {
    ("Image", "imageTopic"): {"foxglove.RawImage", "foxglove.CompressedImage"},
    ("Image", "calibrationTopic"): {"foxglove.CameraCalibration"},
    ("3D", "topics"): {"foxglove.SceneUpdate"},
    ("RosOut", "topicToRender"): {"foxglove.Log"},
}


def _opens_on(layout: dict[str, Any], path: Path) -> None:
    """Every panel of ``layout`` names topics of ``path`` with the schema it draws; every Plot
    path is a numeric field of its topic's stored schema."""
    schemas, frames, descs = _channels(path)
    for pid, cfg in layout["configById"].items():
        kind = pid.split("!")[0]
        named: list[tuple[str, str]] = []
        if kind == "Image":
            named += [(k, v) for k, v in cfg["imageMode"].items() if k.endswith("Topic")]
        if kind == "3D":
            named += [("topics", t) for t in cfg["topics"]]
            assert {frames[t] for t in cfg["topics"]} == {cfg["followTf"]}, pid
        if kind == "RosOut":
            named.append(("topicToRender", cfg["topicToRender"]))
        if kind == "RawMessages":
            assert cfg["topicPath"] in schemas, pid
        for key, topic in named:
            assert schemas[topic] in _PANEL_SCHEMAS[kind, key], (pid, topic)
        for p in cfg.get("paths", []):
            topic = max((t for t in schemas if p["value"].startswith(t + ".")), key=len)
            desc, field = descs[topic], None
            for name in p["value"][len(topic) + 1 :].split("."):
                field = desc.fields_by_name[name]
                desc = field.message_type
            assert field is not None
            assert field.cpp_type not in (field.CPPTYPE_STRING, field.CPPTYPE_MESSAGE), p


# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("use", LAYOUT_USES)
def test_the_layout_written_for_a_file_opens_every_panel_on_it(
    files: dict[LayoutUse, Path], use: LayoutUse, tmp_path: Path
) -> None:
    res = write_layout(files[use], tmp_path / "out.json")
    assert res.use == use
    layout = json.loads(res.path.read_text())
    schemas, frames, _ = _channels(files[use])
    assert layout_problems(layout, schemas, frames=frames) == []
    _opens_on(layout, files[use])
    assert res.panels == len(layout["configById"]) >= 2


@pytest.mark.parametrize("use", LAYOUT_USES)
def test_each_stored_layout_opens_as_it_is_on_the_simulated_rig(
    files: dict[LayoutUse, Path], use: LayoutUse
) -> None:
    stored = layout_template(use)
    schemas, frames, _ = _channels(files[use])
    assert layout_problems(stored, schemas, frames=frames) == []
    _opens_on(stored, files[use])


def test_the_recording_layout_has_an_ir_and_a_depth_panel_per_d415(
    files: dict[LayoutUse, Path],
) -> None:
    schemas, frames, _ = _channels(files["recording"])
    layout = layout_for(schemas, use="recording", frames=frames)
    images = {
        c["imageMode"]["imageTopic"] for c in layout["configById"].values() if "imageMode" in c
    }
    images.discard(None)
    want = {f"/d415/{s}/{k}" for s in (D415_A, D415_B) for k in ("ir", "depth")}
    assert images == {*want, f"/davis/{DAVIS}/frame"}
    counters = [p["value"] for p in layout["configById"]["Plot!framecounter"]["paths"]]
    assert counters == [f"/d415/{s}/frame_info.frame_counter" for s in (D415_A, D415_B)]


def test_the_calibration_layout_shows_each_d415_with_its_intrinsics_and_the_sync_box(
    files: dict[LayoutUse, Path],
) -> None:
    schemas, frames, _ = _channels(files["calibration"])
    cfgs = layout_for(schemas, use="calibration", frames=frames)["configById"]
    infos = sorted(c["topicPath"] for p, c in cfgs.items() if p.startswith("RawMessages!camera"))
    assert infos == [f"/d415/{s}/camera_info" for s in (D415_A, D415_B)]
    ir = sorted(
        (c["imageMode"]["imageTopic"], c["imageMode"]["calibrationTopic"])
        for p, c in cfgs.items()
        if p.startswith("Image!d415ir")
    )
    assert ir == [(f"/d415/{s}/ir", f"/d415/{s}/camera_info") for s in (D415_A, D415_B)]
    assert cfgs["RawMessages!pulses"]["topicPath"] == "/syncbox/pulses"


def test_panels_and_series_of_devices_a_file_lacks_are_left_out() -> None:
    d = f"/d415/{D415_A}"
    schemas = {
        f"{d}/ir": "foxglove.RawImage",
        f"{d}/frame_info": "mocaprig.D415FrameInfo",
        "/diagnostics": "mocaprig.RecorderStatus",
    }
    layout = layout_for(schemas, use="recording")
    assert layout_problems(layout, schemas) == []
    ir = next(c for c in layout["configById"].values() if c.get("imageMode", {}).get("imageTopic"))
    # No camera_info stream: the IR still shows, without the calibration topic.
    assert ir["imageMode"] == {"imageTopic": f"{d}/ir"}
    assert sorted(layout["configById"]) == [
        "Image!d415ir-0",
        "Plot!drops",
        "Plot!framecounter",
        "RawMessages!diagnostics",
    ]


def test_the_3d_panel_follows_the_frame_the_results_are_drawn_in() -> None:
    schemas = {"/democap/joints": "foxglove.SceneUpdate"}
    frames = {"/democap/joints": "lab"}
    layout = layout_for(schemas, use="democap", frames=frames)
    view = layout["configById"]["3D!democap"]
    assert view["topics"] == {"/democap/joints": {"visible": True}}
    assert view["followTf"] == "lab"
    assert view["layers"]["grid"]["frameId"] == "lab"
    assert layout_problems(layout, schemas, frames=frames) == []


def test_problems_name_the_topic_schema_and_field_that_do_not_fit(
    files: dict[LayoutUse, Path],
) -> None:
    schemas, frames, _ = _channels(files["recording"])
    layout = layout_for(schemas, use="recording", frames=frames)
    cfg = layout["configById"]
    cfg["Image!d415ir-0"]["imageMode"]["imageTopic"] = f"/d415/{D415_A}/frame_info"
    cfg["Plot!drops"]["paths"][0]["value"] = "/diagnostics.dropped"
    cfg["Plot!syncpulses"]["paths"][0]["value"] = "/syncbox/pulses.mode"
    cfg["RosOut!log"]["topicToRender"] = "/nope"
    problems = "\n".join(layout_problems(layout, schemas, frames=frames))
    assert "is mocaprig.D415FrameInfo; the panel draws" in problems
    assert "no field path 'dropped'" in problems
    assert "'mode' is not a numeric field" in problems
    assert "'/nope' is not a topic of the file" in problems
    assert len(problems.splitlines()) == 4


def test_a_file_without_devices_or_results_gets_no_layout() -> None:
    with pytest.raises(ValidationError, match="no layout fits"):
        choose_use({"/diagnostics": "mocaprig.RecorderStatus"}, [])


def test_info_layout_writes_next_to_the_file_and_overwrites_only_when_asked(
    files: dict[LayoutUse, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "take.mcap"
    src.write_bytes(files["eventcap"].read_bytes())
    assert main(["info", str(src), "--layout"]) == 0
    out = tmp_path / "take.layout.json"
    assert f"{out}: eventcap layout" in capsys.readouterr().out
    first = out.read_text()
    assert json.loads(first)["layout"]["first"] == "3D!eventcap"
    assert main(["info", str(src), "--layout"]) == 1
    assert "pass --overwrite" in capsys.readouterr().err
    assert main(["info", str(src), "--layout", "--overwrite"]) == 0
    assert f"{out}: eventcap layout" in capsys.readouterr().out
    assert out.read_text() == first
    other = tmp_path / "mine.json"
    assert main(["info", str(src), "--layout", str(other), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {
        "layout": str(other),
        "use": "eventcap",
        "panels": 2,
    }
