"""Simulation: worlds, routes, motion and sensors for wiremap."""
