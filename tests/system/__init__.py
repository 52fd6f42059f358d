"""End to end: the daemon and replay with real peers, goldens, damage, security, load."""
