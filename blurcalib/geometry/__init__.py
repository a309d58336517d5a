"""Rotations and other geometry shared by the solvers."""
