"""`xyzcyl client ...`: subcommands that talk to a running server over HTTP (clients/client.py)."""
