"""What leaves the service: NMEA 0183 sentences and JSON records (:mod:`.nmea`,
:mod:`.records`), the outputs that carry them (:mod:`.sinks`) and the fan-out to those
(:mod:`.publish`).
"""
