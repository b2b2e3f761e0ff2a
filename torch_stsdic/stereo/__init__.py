"""Stereo STS-DIC: 3D shape, displacement and velocity from two cameras (see docs/stereo.md)."""
