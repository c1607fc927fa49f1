"""The body model: skeleton, kinematics, shape, surface and marker set."""
