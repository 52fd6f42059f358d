"""The ``bdsfix`` command line: one module per subcommand, the only place that wires drivers to
the engine.
"""
