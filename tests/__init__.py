"""bdsfix tests: one folder per room of the package (core, engine, output, daemon, commands,
studies, sim, drivers), system/ for end-to-end runs of the daemon and replay, support/ for
shared helpers and golden/ for the golden replay outputs."""
