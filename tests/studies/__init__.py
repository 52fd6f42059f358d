"""Tests of service.studies: coverage, TTFF and integrity studies."""
