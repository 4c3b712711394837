"""`xyzcyl` subcommands that need the train extra (torch)."""
