"""Kinematic hand model, geometry and the shared damped Gauss-Newton IK solver."""
