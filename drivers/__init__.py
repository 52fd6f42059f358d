"""Byte sources and protocol parsers that turn receiver data into typed events.

Drivers never do positioning: they frame and parse receiver messages and map them to the
event types in :mod:`service.core.types`. Each stream protocol is one module (its framing
and its mapper) with one entry in :data:`drivers.protocols.PROTOCOLS`.
"""
