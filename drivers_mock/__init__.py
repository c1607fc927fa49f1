"""The simulated world and the mock devices that plug in at the real boundaries.

Mocks emulate devices from their specifications (``../shared/docs``), not from the drivers'
constants. Nothing in ``acquire``, ``calib`` or ``process`` imports this package.
"""
