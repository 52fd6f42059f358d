"""The positioning engine: the fast-fix and SPP solver, RAIM, the frame-sync tracker and the
per-epoch pipeline. It never imports drivers, outputs, the daemon or the commands.
"""
