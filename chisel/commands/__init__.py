"""CLI subcommand modules; each provides ``register(subparsers)`` (see ``chisel.cli``)."""
