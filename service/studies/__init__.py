"""Studies run on the engine: the paper's coverage study and time-to-first-fix trials."""
