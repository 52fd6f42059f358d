"""Tests of service.output: records, NMEA, publishers."""
