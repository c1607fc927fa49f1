"""The simulated world and the mock devices that plug in at the real boundaries.

Mocks emulate devices from their specifications (``../shared/docs``), not from the drivers'
constants. Nothing in ``acquire``, ``calib`` or ``process`` imports this package.
"""

from __future__ import annotations

from mocaprig.drivers_mock.clapperboard import CLAPPER_MARKERS, Clapperboard, make_clapperboard
from mocaprig.drivers_mock.clock import DeviceClock, d415_clock, davis_clock, vicon_clock
from mocaprig.drivers_mock.d415 import MockD415, MockD415Rig, mock_cameras
from mocaprig.drivers_mock.davis240c_sim import DavisSimulator, simulate_davis
from mocaprig.drivers_mock.davis240c_usb import Davis240CBackend, DavisFaults, mock_backend
from mocaprig.drivers_mock.noise import NoiseSettings
from mocaprig.drivers_mock.rig import (
    D415Spec,
    DavisSpec,
    PinholeCamera,
    Rig,
    ViconSpec,
    default_rig,
    look_at,
    project,
)
from mocaprig.drivers_mock.scenario import SCENARIOS, Scenario, WorldSample, build_scenario
from mocaprig.drivers_mock.session import SimulationResult, simulate_session
from mocaprig.drivers_mock.syncbox import MockSyncBox, mock_syncbox
from mocaprig.drivers_mock.truth import Truth, ViconTruth, read_truth, write_truth
from mocaprig.drivers_mock.vicon import ViconCapture, simulate_vicon, write_c3d, write_nexus_csv

__all__ = [
    "CLAPPER_MARKERS",
    "SCENARIOS",
    "Clapperboard",
    "D415Spec",
    "Davis240CBackend",
    "DavisFaults",
    "DavisSimulator",
    "DavisSpec",
    "DeviceClock",
    "MockD415",
    "MockD415Rig",
    "MockSyncBox",
    "NoiseSettings",
    "PinholeCamera",
    "Rig",
    "Scenario",
    "SimulationResult",
    "Truth",
    "ViconCapture",
    "ViconSpec",
    "ViconTruth",
    "WorldSample",
    "build_scenario",
    "d415_clock",
    "davis_clock",
    "default_rig",
    "look_at",
    "make_clapperboard",
    "mock_backend",
    "mock_cameras",
    "mock_syncbox",
    "project",
    "read_truth",
    "simulate_davis",
    "simulate_session",
    "simulate_vicon",
    "vicon_clock",
    "write_c3d",
    "write_nexus_csv",
    "write_truth",
]
