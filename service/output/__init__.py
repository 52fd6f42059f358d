"""What leaves the service: NMEA 0183, the JSON/CSV records and the sinks (NMEA TCP, ZeroMQ,
files).
"""
