"""Byte sources and protocol parsers that turn receiver data into typed events.

Drivers never do positioning: they map library-parsed messages to the event types in
:mod:`service.core.types`.
"""
