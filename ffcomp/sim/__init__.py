"""Simulation: nonlinear plant, Klipper input shapers, tracking-error metrics, bench."""
