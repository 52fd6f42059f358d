"""Tests of service.sim: Keplerian constellations and the simulated scenario."""
