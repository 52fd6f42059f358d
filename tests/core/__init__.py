"""Tests of service.core: navigation codec, time, orbit, geometry, ephemerides."""
