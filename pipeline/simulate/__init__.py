"""The chamber-run simulator: programs, the simulated unit, runs in memory or in chunks."""
