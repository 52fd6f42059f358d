"""The shared vocabulary: measurement and ephemeris types, time, constants, errors, geometry,
orbits, corrections, the D1/D2 codec and the ephemeris store. Drivers and every room of the
service may import it; it imports nothing else of bdsfix.
"""
