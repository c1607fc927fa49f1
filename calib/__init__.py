"""Vicon I/O, marker measurement, time alignment, registration and intrinsics."""
