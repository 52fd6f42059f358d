"""Helpers shared by the tests: not tests themselves, and never importing a test or bench/.

- :mod:`tests.support.paths`: the repository root, the recordings (``../shared/data``) and
  the golden replay outputs;
- :mod:`tests.support.independent`: independent references (georinex, the ICD algorithm);
- :mod:`tests.support.fixes`: realistic hand-built fixes and sky views;
- :mod:`tests.support.nmea`: an independent NMEA 0183 parser and time helpers;
- :mod:`tests.support.schema`: records checked against the JSON Schemas with jsonschema;
- :mod:`tests.support.load`: the load harness (also run by bench/bench_load.py).
"""
