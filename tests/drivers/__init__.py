"""Tests of drivers: framing, UBX, RTCM3, RINEX, SFRBX, transports, fuzzing."""
