"""Tests of service.engine: solver, integrity (RAIM/FDE), pipeline."""
