"""End-to-end tests: whole commands across packages, on the simulated rig."""
