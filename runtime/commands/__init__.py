"""Local `xyzcyl` subcommands backed by the runtime (no torch)."""
