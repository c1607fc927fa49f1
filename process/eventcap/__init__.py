"""EventCap: 3D human motion at 1000 fps from one DAVIS240C (Xu et al., CVPR 2020).

The method, its stages and the measured figures are in docs/eventcap.md.

Stages per batch (the interval between two APS frames):

* :mod:`.edi` — event-based double integral: sharp APS frames and latent images at any time.
* :mod:`.tracking` — features tracked on latent images forward and backward, stitched at
  mid-batch, smoothed by B-splines and sampled at 1 kHz.
* :mod:`.detections` — 2D/3D joint detections at the APS frames through one ``Detector``
  protocol (OpenPose/COCO JSON, a synthetic detector for simulated sessions).
* :mod:`.camera` — the one camera record every stage uses.
* :mod:`.raster` — the capsule template rasterised at the sensor size (silhouette, part ids,
  surface points).
* :mod:`.event_index` and :mod:`.refine` — closest events per silhouette pixel and the
  event-based silhouette refinement (paper Eqs. 9–13).
* :mod:`.pipeline` — one batch end to end; :mod:`.take` — a whole take, batches streamed.
* :mod:`.evaluate` — EventCap and the paper's baselines against ground truth.
* :mod:`.ecd` — takes in the RPG Event-Camera Dataset layout.
* :mod:`.run` — ``mocaprig eventcap run``: a recording in, 1 kHz results (MCAP, C3D, BVH) out.
* :mod:`.batch_fit` — the hybrid batch optimisation (paper Eqs. 3–8).
* :mod:`.metrics` — AE (MPJPE after Procrustes), absolute MPJPE, Size.sec.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from mocaprig.lazy_exports import lazy_getattr

if TYPE_CHECKING:
    from mocaprig.process.eventcap.batch_fit import (
        BatchFitOptions,
        BatchFitResult,
        Correspondences,
        FrameDetections,
        fit_batch,
        fit_frame,
        interpolate_poses,
        linear_baseline,
    )
    from mocaprig.process.eventcap.camera import EventCamera
    from mocaprig.process.eventcap.detections import (
        CocoKeypointDetections,
        Detection,
        Detector,
        JsonDetections,
        OpenPoseJsonDetections,
        SyntheticDetections,
        SyntheticNoise,
        write_detections_json,
    )
    from mocaprig.process.eventcap.ecd import EcdTake, read_ecd_take
    from mocaprig.process.eventcap.edi import EdiBatch, LinearResponse, SharpFrame, TableResponse
    from mocaprig.process.eventcap.evaluate import EventcapEvaluation, TakeWithTruth, evaluate_take
    from mocaprig.process.eventcap.event_index import EventIndex, build_event_index, closest_events
    from mocaprig.process.eventcap.metrics import (
        DataRate,
        TrackingErrors,
        data_rate,
        evaluate_tracking,
        upsample_linear,
    )
    from mocaprig.process.eventcap.pipeline import (
        ApsFrame,
        BatchResult,
        EventcapOptions,
        frame_detections,
        run_batch,
    )
    from mocaprig.process.eventcap.raster import Raster, rasterize
    from mocaprig.process.eventcap.refine import RefineOptions, refine_frame, refine_frames
    from mocaprig.process.eventcap.run import (
        EventcapResultsWriter,
        EventcapRunResult,
        ResultsHeader,
        run_eventcap,
    )
    from mocaprig.process.eventcap.take import (
        EventSource,
        TakeChunk,
        TakeResult,
        array_source,
        iter_take,
        run_take,
    )
    from mocaprig.process.eventcap.tracking import TrackingOptions, TrackingResult, track_frames

#: The public names by submodule, imported on first use (:mod:`mocaprig.lazy_exports`).
_EXPORTS: dict[str, tuple[str, ...]] = {
    "batch_fit": (
        "BatchFitOptions",
        "BatchFitResult",
        "Correspondences",
        "FrameDetections",
        "fit_batch",
        "fit_frame",
        "interpolate_poses",
        "linear_baseline",
    ),
    "camera": ("EventCamera",),
    "detections": (
        "CocoKeypointDetections",
        "Detection",
        "Detector",
        "JsonDetections",
        "OpenPoseJsonDetections",
        "SyntheticDetections",
        "SyntheticNoise",
        "write_detections_json",
    ),
    "ecd": (
        "EcdTake",
        "read_ecd_take",
    ),
    "edi": (
        "EdiBatch",
        "LinearResponse",
        "SharpFrame",
        "TableResponse",
    ),
    "evaluate": (
        "EventcapEvaluation",
        "TakeWithTruth",
        "evaluate_take",
    ),
    "event_index": (
        "EventIndex",
        "build_event_index",
        "closest_events",
    ),
    "metrics": (
        "DataRate",
        "TrackingErrors",
        "data_rate",
        "evaluate_tracking",
        "upsample_linear",
    ),
    "pipeline": (
        "ApsFrame",
        "BatchResult",
        "EventcapOptions",
        "frame_detections",
        "run_batch",
    ),
    "raster": (
        "Raster",
        "rasterize",
    ),
    "refine": (
        "RefineOptions",
        "refine_frame",
        "refine_frames",
    ),
    "run": (
        "EventcapResultsWriter",
        "EventcapRunResult",
        "ResultsHeader",
        "run_eventcap",
    ),
    "take": (
        "EventSource",
        "TakeChunk",
        "TakeResult",
        "array_source",
        "iter_take",
        "run_take",
    ),
    "tracking": (
        "TrackingOptions",
        "TrackingResult",
        "track_frames",
    ),
}
__getattr__ = lazy_getattr(__name__, _EXPORTS)

__all__ = [
    "ApsFrame",
    "BatchFitOptions",
    "BatchFitResult",
    "BatchResult",
    "CocoKeypointDetections",
    "Correspondences",
    "DataRate",
    "Detection",
    "Detector",
    "EcdTake",
    "EdiBatch",
    "EventCamera",
    "EventIndex",
    "EventSource",
    "EventcapEvaluation",
    "EventcapOptions",
    "EventcapResultsWriter",
    "EventcapRunResult",
    "FrameDetections",
    "JsonDetections",
    "LinearResponse",
    "OpenPoseJsonDetections",
    "Raster",
    "RefineOptions",
    "ResultsHeader",
    "SharpFrame",
    "SyntheticDetections",
    "SyntheticNoise",
    "TableResponse",
    "TakeChunk",
    "TakeResult",
    "TakeWithTruth",
    "TrackingErrors",
    "TrackingOptions",
    "TrackingResult",
    "array_source",
    "build_event_index",
    "closest_events",
    "data_rate",
    "evaluate_take",
    "evaluate_tracking",
    "fit_batch",
    "fit_frame",
    "frame_detections",
    "interpolate_poses",
    "iter_take",
    "linear_baseline",
    "rasterize",
    "read_ecd_take",
    "refine_frame",
    "refine_frames",
    "run_batch",
    "run_eventcap",
    "run_take",
    "track_frames",
    "upsample_linear",
    "write_detections_json",
]
