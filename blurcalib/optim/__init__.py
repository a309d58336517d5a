"""Numerical optimisation shared by the engine's fits: the damped least-squares driver."""
