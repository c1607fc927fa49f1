"""Time alignment of the rig's device clocks onto the reference (Vicon) clock.

The recipe (calibration-vicon.md §3.1, §0 items 11–12):

1. **Claps** give a coarse offset per device. The clapperboard's two markers sit at their
   contact distance most of the time; a clap opens them (hundreds of mm), holds, and closes them
   back to contact. The clap instant is the contact instant.

   * Vicon (:func:`find_claps_vicon`, 100–120 Hz): the distance of the two labelled clapper
     markers; the contact time is where a quadratic fitted to the last pre-contact samples of
     the closing reaches the contact distance (sub-frame; ≈ 0.2 ms).
   * D415 (:func:`find_claps_d415`, 30 Hz, unlabelled markers): the clapper is found as the
     pair of *static* blobs a contact distance apart of which one leaves and comes back; the
     signal is the image distance (px) of the moving marker from the fixed one (the image is
     far more precise than D415 depth). A 30 Hz camera sees only 1–4 samples of a 60–120 ms
     closing, so the closing *trajectory* is fitted: constant angular acceleration from rest
     (``θ = θmax·(1 − u²)``, ``u`` from 0 to 1 over the closing), the signal taken as linear in
     ``θ``, evaluated as a posterior over (contact time, closing duration) on a grid with a weak
     prior on the duration; the estimate is the posterior mean and ``sigma_ns`` its spread.
   * DAVIS (:func:`find_claps_davis`): the clapper's arm sweeps a burst of events that stops
     dead at contact; the contact is the sharpest fall of the event rate of the busiest image
     cell, located to the event-rate bin.

2. **Clock from claps** (:func:`clock_from_claps`): offset from one clap, offset and drift from
   two or more (a weighted line through the clap pairs).

3. **Refinement.** The D415 claps are only good to a few ms and two claps cannot give a drift
   to ppm, so the mapping is refined over the whole session:

   * :func:`refine_by_reprojection` (accurate; needs the camera's registered pose): the Vicon
     markers interpolated at each frame's mapped time are projected onto the frame's blobs and
     the offset and drift corrections fitted to the image residuals (≈ 0.2 ms on the simulated
     sessions; see docs/calibration.md for the drift);
   * :func:`refine_by_speed` (no extrinsics): a normalised cross-correlation of marker-speed
     signals over a grid of offsets (the prior), then the correlation maximised over a
     continuous offset and drift. Speeds are rotation-invariant: :func:`speed_from_trajectories`
     (Vicon, labelled markers) and :func:`speed_from_frames` (one D415's
     :class:`~calib.markers.MarkerFrame` list, nearest-neighbour matching in the image, lateral
     speed from the image motion and depth). The two signals differ in shape, which biases the
     peak by milliseconds on the simulated sessions: a coarse prior only.

4. **Pulses** (:func:`clock_from_pulses`): the D415 master's frame pulses reach the DAVIS's
   external input, so DAVIS ↔ D415 is a line fitted through paired pulses and frames (µs-level),
   composed with the D415's mapping to reach the reference.

5. **Sync channel** (:func:`find_sync_edges`, :func:`clock_from_sync_edges`): the sync box's
   toggle output (one edge per D415 master pulse, docs/wiring.md §7) recorded on a Vicon analog
   input, i.e. sampled on the Vicon clock. Edges: mid-level crossings interpolated linearly
   between samples; a filtered (RC) edge crosses mid-level a delay after it switched, which is
   measured from the samples after each crossing (the decay towards the final level gives the
   time constant τ; each edge's switching instant is then exact for a first-order edge).
   Edges are paired with the master's frames through a prior mapping good to a quarter period
   (the video clock), and a line device → Vicon is fitted: µs-level offset and sub-ppm drift.

Clock mappings are :class:`mocaprig.calib.calibration.ClockMapping`:
``t_ref = t_dev + offset_ns + drift_ppm·1e-6·(t_dev − anchor_ns)``.

The steps live in modules of their own; this module re-exports their public names, so
``from mocaprig.calib.time_align import X`` works for all of them:

- :mod:`mocaprig.calib.vicon_times`: Vicon-clock times of frames and analog samples;
- :mod:`mocaprig.calib.clap_detection`: :class:`ClapDetection`, the Vicon and DAVIS claps;
- :mod:`mocaprig.calib.clap_detection_d415`: the D415 claps (tracking, closing fit);
- :mod:`mocaprig.calib.clock_fit`: clocks from claps and from pulses;
- :mod:`mocaprig.calib.time_refine_speed`: speed signals and the speed refinement;
- :mod:`mocaprig.calib.time_refine_reprojection`: the reprojection refinement;
- :mod:`mocaprig.calib.sync_edges`: the sync channel's edges and the clock through them.
"""

from __future__ import annotations

from mocaprig.calib.clap_detection import (
    VICON_CLAPPER_LABELS,
    ClapDetection,
    find_claps_davis,
    find_claps_vicon,
)
from mocaprig.calib.clap_detection_d415 import find_claps_d415
from mocaprig.calib.clock_fit import clock_from_claps, clock_from_pulses
from mocaprig.calib.sync_edges import SyncEdges, clock_from_sync_edges, find_sync_edges
from mocaprig.calib.time_refine_reprojection import _project as _project  # tests reach it here
from mocaprig.calib.time_refine_reprojection import refine_by_reprojection
from mocaprig.calib.time_refine_speed import (
    refine_by_speed,
    speed_from_frames,
    speed_from_trajectories,
)
from mocaprig.calib.vicon_times import analog_times_ns, vicon_times_ns

__all__ = [
    "VICON_CLAPPER_LABELS",
    "ClapDetection",
    "SyncEdges",
    "analog_times_ns",
    "clock_from_claps",
    "clock_from_pulses",
    "clock_from_sync_edges",
    "find_claps_d415",
    "find_claps_davis",
    "find_claps_vicon",
    "find_sync_edges",
    "refine_by_reprojection",
    "refine_by_speed",
    "speed_from_frames",
    "speed_from_trajectories",
    "vicon_times_ns",
]
