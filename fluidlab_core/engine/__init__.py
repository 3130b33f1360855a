"""Simulation engine: MLS-MPM solver pieces and the geometry helpers they use."""
