"""Periodic-equilibrium identification of nonlinear dynamic models (pure numerics)."""

__version__ = "0.1.0"
